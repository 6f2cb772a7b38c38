"""mmpgo-jax: distributed pose graph optimization by majorization minimization, in JAX."""

from ._geometry import project_to_so, quaternion_to_rotation, rotation_2d
from ._pose_graph import (
    PoseGraph,
    Poses,
    connected_components,
    cost,
    data_matrix,
    edge_costs,
    euclidean_gradient,
    matrix_to_poses,
    objective,
    poses_to_matrix,
    riemannian_gradient,
    riemannian_gradient_norm,
)
from ._precision import default_float_dtype, enable_float64, float64_enabled

__version__ = "0.1.0"
