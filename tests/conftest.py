"""Test-session settings: one torch thread.

The suite's tensors are small; on a shared 2-core machine torch's thread pool spends
more time synchronising than computing (a gradient fit ran ten times slower with two
threads under load), and one thread makes every float sum run in one order.
"""

import torch

torch.set_num_threads(1)
