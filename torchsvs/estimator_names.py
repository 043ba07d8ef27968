"""The estimators of ``torchsvs track --estimator`` by name (:data:`ESTIMATORS`), built by
:mod:`torchsvs.recipes`. Apart from the recipes so that the command line lists them without
importing torch: its input is read meanwhile (:class:`~torchsvs.datasets.reading.ReadAhead`).
"""

#: Estimator names of ``torchsvs track --estimator`` and what they are.
ESTIMATORS = {
    "auto": "the lowest estimated error of ks, svss, imm (small "
    "files), each tuned on the file without truth (torchsvs.selection)",
    "kf": "Kalman filter",
    "ks": "Kalman smoother (RTS; fixed interval unless --lag)",
    "svsf": "smooth variable structure filter",
    "svss": "smooth variable structure smoother (fixed interval unless --lag)",
    "svstps": "two-pass smoother: RTS over the SVSF (fixed interval unless --lag)",
    "ekf": "extended Kalman filter (the KF on this linear model)",
    "ukf": "unscented Kalman filter (the KF on this linear model)",
    "rstkf": "robust Student's t Kalman filter",
    "pf": "SIR particle filter",
    "spvsf": "smooth particle variable structure filter",
    "imm": "IMM of a KF on constant velocity and an EKF on a coordinated turn (horizontal)",
}
