"""The small-function layer (cuthbert's ``cuthbertlib`` beside its assembled filters).

Each module holds one kind of building block, tested on its own against a dense or closed-form
reference (``tests/test_lib.py``); the updates, gains and filters of the package assemble them:

- ``static``: builders' pure functions bound to static structure and traced numbers (``bind``);
- ``validation``: argument checks at the API boundary, with errors that name the argument;
- ``linalg``: symmetrise, PSD square roots, truncated pseudo-inverse solves;
- ``gaussian``: Gaussian conditioning (the Kalman gain) through a Cholesky factor;
- ``ensemble``: (masked, weighted) ensemble means, anomalies, standard deviations, covariances;
- ``transform``: the ETKF's ensemble transform (global square-root EnKF and LETKF);
- ``weights``: log-weight normalisation and the effective sample size;
- ``fallback``: "use the fallback where the primary result failed", over pytrees.
"""
