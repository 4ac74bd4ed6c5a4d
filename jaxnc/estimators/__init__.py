"""State estimators' kernels: EKF, UKF, steady-state observers."""
from jaxnc.estimators.ekf import Gaussian, ekf_predict, ekf_update
from jaxnc.estimators.sparsity import EKFStructure, Pattern, detect_structure
from jaxnc.estimators.steady_state import dlqe, luenberger_step
from jaxnc.estimators.ukf import SigmaPoints, merwe_sigma_points, ukf_predict, ukf_update

__all__ = ["Gaussian", "ekf_predict", "ekf_update",
           "EKFStructure", "Pattern", "detect_structure",
           "dlqe", "luenberger_step",
           "SigmaPoints", "merwe_sigma_points", "ukf_predict", "ukf_update"]
