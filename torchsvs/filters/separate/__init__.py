"""The separate-modeling (SM) tracker of Zhang & Zhou (2022) for road targets, and its
online-fitting baseline, as batched, differentiable functions and modules of tensors.

- :mod:`~torchsvs.filters.separate.initialisation`: the augmented state from the first three
  measurements by the unscented transform (Eqs. (17)-(21)).
- :mod:`~torchsvs.filters.separate.reset`: the least-squares reset of the trajectory
  parameters over a sliding window (Eqs. (36)-(40)) and its covariance.
- :mod:`~torchsvs.filters.separate.tracker`: :class:`~torchsvs.SeparateModelingTracker`, the
  IMM of the NCV and NCA augmented models with the reset in its interaction hooks.
- :mod:`~torchsvs.filters.separate.online_fitting`: the paper's online-fitting baseline (its
  ref. [30]), a line in time per axis over the window; not part of the tracker.

The paper's equations were lost in extraction; each module rebuilds its part from the paper's
text and the cited literature. The guide ``docs/guide/separate_modeling.md`` says why the
tracker is built as it is.

References:
    Zhang Zhuanhua, Zhou Gongjian, J. Syst. Eng. Electron. 33(5), 2022.
"""
