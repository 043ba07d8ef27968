"""Fitting estimators on recorded tracks without truth, and without Lightning.

* :mod:`~torchsvs.fitting.losses`: the losses (innovation NLL, Stein's unbiased risk estimate,
  ...) and :mod:`~torchsvs.fitting.batches`: recorded tracks cut into windows with priors.
* :mod:`~torchsvs.fitting.noise`: ``q`` by the Kalman smoother's exact SURE, per file and per
  track.
* :mod:`~torchsvs.fitting.defaults`: the settings ``torchsvs track`` reads off the data.
* :mod:`~torchsvs.fitting.tuning`: :func:`~torchsvs.fitting.tuning.self_tune`, ``--fit``.

Nothing is imported here, so that importing one part (e.g. ``torchsvs.fitting.noise``) does not
import the others. :mod:`torchsvs.estimating` uses these parts; ``--estimator auto``, which
scores fitted candidates as :mod:`torchsvs.estimating` runs them, sits above both
(:mod:`torchsvs.selection`).
"""
