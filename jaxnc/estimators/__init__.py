"""State estimators: EKF and the NUDREKF of seed 000."""
from jaxnc.estimators.ekf import Gaussian, ekf_predict, ekf_update
from jaxnc.estimators.nudrekf import nudrekf_correct, predict_horizon
from jaxnc.estimators.sparsity import EKFStructure, Pattern, detect_structure

__all__ = ["Gaussian", "ekf_predict", "ekf_update", "nudrekf_correct", "predict_horizon",
           "EKFStructure", "Pattern", "detect_structure"]
