"""The paper's experiments as a library."""
