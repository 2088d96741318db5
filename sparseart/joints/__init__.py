"""Joint fitting: cleaning, one prepared sample per part, the joint fit, type selection,
uncertainty, reliability warnings, and the candidate search over seed motions.

Modules (one concern each): ``config`` (FitConfig, budgets), ``part`` (prepare_part: cleaning,
normalisation, the shared subsamples), ``models`` (revolute / prismatic parameterisations),
``seeds`` (initial motion, seed screening), ``optimise`` (matching, robust solve, covariance ->
ModelFit), ``select`` (type choice), ``uncertainty`` (stated sigma), ``reliability`` (warning
codes, confidence), ``fit`` (fit_joint, the orchestration), ``clean``, ``candidates``,
``siblings`` (whole-object consistency: look-alike parts slide alike).

Public entry points::

    fit_joint(start_points, end_points, joint_type="auto", ..., config=FitConfig.for_budget("fast")) -> JointEstimate
    screen_seeds(start_points, end_points, seeds, joint_type="auto") -> list[SeedScreen]
    register_rigid(source, target, ...) -> RigidRegistration
    clean_part_points(points) -> bool mask
"""
from sparseart.geometry.icp import RigidRegistration, register_rigid
from sparseart.geometry.transforms import (
                                    Screw,
                                    kabsch,
                                    robust_kabsch,
                                    screw_from_transform,
                                    transform_from_prismatic,
                                    transform_from_revolute,
)
from sparseart.joints.clean import clean_part_points
from sparseart.joints.config import BUDGETS, FitConfig
from sparseart.joints.fit import fit_joint
from sparseart.joints.reliability import FitWarning, WarningCode
from sparseart.joints.seeds import SeedScreen, screen_seeds
from sparseart.joints.select import bic, select_joint_type

__all__ = [
    "BUDGETS", "FitConfig", "FitWarning", "RigidRegistration", "Screw", "SeedScreen", "WarningCode", "bic",
    "clean_part_points", "fit_joint", "kabsch", "register_rigid", "robust_kabsch", "screen_seeds",
    "screw_from_transform", "select_joint_type", "transform_from_prismatic", "transform_from_revolute",
]
