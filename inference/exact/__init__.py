"""The engine floor: the exact sums that fitting and the questions both use.

:mod:`~inference.exact.enumeration` (:func:`~inference.exact.enumeration.enumerate_model`,
the entry point: the model traced and every latent discrete site summed out) over
:mod:`~inference.exact.traced` (one trace and its factors) and
:mod:`~inference.exact.unknown_initial` (a continuous initial feature left out of the
evidence, integrated out in closed form by the joint Gaussian of
:mod:`~inference.exact.gaussian_gaps`, which EM's E-step reads too);
:mod:`~inference.exact.elimination` and :mod:`~inference.exact.factored` sum a sparse
network one site at a time; :mod:`~inference.exact.paths` sums over the steps of a
chain. Nothing here imports :mod:`inference.fitting`, :mod:`inference.queries` or
:mod:`inference.sequences`.
"""
