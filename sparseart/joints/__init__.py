"""Joint fitting: stable screw maps, rigid registration, cleaning, joint fit and type selection.

Public entry points::

    fit_joint(start_points, end_points, joint_type="auto", ...) -> JointEstimate
    register_rigid(source, target, ...) -> RigidRegistration
    clean_part_points(points) -> bool mask
"""
from sparseart.joints.clean import clean_part_points
from sparseart.joints.fit import FitConfig, fit_joint
from sparseart.geometry.icp import RigidRegistration, register_rigid
from sparseart.geometry.transforms import (Screw, kabsch, robust_kabsch, screw_from_transform, transform_from_prismatic,
                                    transform_from_revolute)
from sparseart.joints.select import bic, select_joint_type

__all__ = [
    "FitConfig", "RigidRegistration", "Screw", "bic", "clean_part_points", "fit_joint", "kabsch",
    "register_rigid", "robust_kabsch", "screw_from_transform", "select_joint_type",
    "transform_from_prismatic", "transform_from_revolute",
]
