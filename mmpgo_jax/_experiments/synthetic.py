"""Seeded synthetic pose-graph datasets with ground truth (the paper's "Cube" datasets, Fig. 1).

Generative model (SE-Sync's, Rosen et al. 2016, Eq. (10); the paper's Section VIII.A)
-------------------------------------------------------------------------------------
For every edge (i, j) with ground-truth poses (R_i, t_i), (R_j, t_j)::

    R~_ij = R_i^T R_j  R^eps,      R^eps ~ Langevin(I_d, kappa)
    t~_ij = R_i^T (t_j - t_i) + t^eps,   t^eps ~ N(0, tau^{-1} I_d)

``Langevin(M, kappa)`` is the isotropic Langevin (matrix von Mises-Fisher) distribution on SO(d)
with density ``p(R) = exp(kappa tr(M^T R)) / c_d(kappa)`` with respect to the Haar (uniform)
probability measure.  With this convention the negative log-likelihood of a measurement is
``kappa/2 ||R_i R~ - R_j||_F^2 + tau/2 ||R_i t~ + t_i - t_j||^2 + const``, i.e. exactly half of the
per-edge term of ``f = 2F`` (:func:`mmpgo_jax.cost`), and the graph's weights are the ``kappa``,
``tau`` used to generate the noise.

Samplers (exact, no approximations):

* d = 2: ``R = Rot(theta)``, ``tr R = 2 cos(theta)``, Haar = uniform angle, so ``theta`` is von
  Mises with concentration ``2 kappa`` (numpy's Best-Fisher sampler).
* d = 3: with a unit quaternion ``q = (v, w)``, ``tr R = 4 w^2 - 1`` and Haar on SO(3) is the
  uniform measure on S^3 (double cover), so ``q`` is Bingham with density
  ``exp(-4 kappa |v|^2)``; sampled by rejection from an angular central Gaussian envelope (Kent,
  Ganeiber & Mardia 2013), whose acceptance rate stays above ~0.5 for every kappa.  Equivalently
  the rotation angle has density proportional to ``(1 - cos theta) exp(2 kappa cos theta)`` on
  [0, pi] and the axis is uniform.

Noise level -> weights (:func:`kappa_tau_from_rmse`)
----------------------------------------------------
"Expected translational RMSE sigma_t" is ``sqrt(E ||t^eps||^2)``; since ``E ||t^eps||^2 = d / tau``,
``tau = d / sigma_t^2``.  "Expected angular RMSE sigma_R" is ``sqrt(E theta^2)`` with ``theta`` the
geodesic angle of ``R^eps``; ``E theta^2`` is computed by quadrature from the angle densities above
and inverted for kappa by root finding (it decreases monotonically in kappa; for small noise
``E theta^2 ~ d(d-1)/2 / (2 kappa)``, i.e. ``kappa ~ d(d-1) / (4 sigma_R^2)``).  The achievable
RMSE is bounded by the uniform (kappa = 0) value: ``pi/sqrt(3)`` (d = 2), ``sqrt(pi^2/3 + 2)``
(d = 3).  For sigma_t = 0.02 m and sigma_R = 0.02 pi rad:

* d = 3: tau = 7500, kappa = 380.288 (small-noise approximation 3 / (2 sigma_R^2) = 379.954);
* d = 2: tau = 5000, kappa = 126.902 (small-noise approximation 1 / (2 sigma_R^2) = 126.651).

Expected cost at the ground truth: per edge
``E[kappa ||R^eps - I||^2 + tau ||t^eps||^2] = 2 kappa (d - E tr R^eps) + d`` with
``E tr R^eps = 2 I1(2k)/I0(2k)`` (d = 2) and ``-1 + I1(2k) / (k (I0(2k) - I1(2k)))`` (d = 3),
which tends to ``d(d-1)/2 + d`` (3 in 2D, 6 in 3D) for small noise
(:func:`expected_edge_cost`).

Path model (documented choice; the paper only says "a path of 3600 poses along the rectilinear
edges of the cube grid")
-------------------------------------------------------------------------------------------------
* Lattice: ``grid`` cells of side ``side`` per axis, i.e. vertices ``side * {0, ..., grid}^d``
  ((grid + 1)^d vertices; the cube spans ``grid * side`` metres).
* The walk starts at the origin corner.  Each step moves to a neighbouring lattice vertex
  (+-1 cell along one axis) chosen uniformly among those inside the lattice, excluding the
  immediate reversal of the previous step (there is always another option when d >= 2).
* Orientation = heading of travel: the first axis of ``R_k`` points along the step leaving pose
  k (the last pose keeps the heading of the step arriving at it).  The remaining axes are carried
  along by parallel transport: on a turn the frame is rotated by the 90-degree rotation in the
  plane of the old and new headings (a vehicle turning), and the initial frame is the minimal
  rotation taking e_1 to the first heading (a pi rotation in the e_1-e_2 plane if it is -e_1).
  Every ``R_k`` is a proper rotation; odometry then reads "forward ``side`` metres, then turn".
* Odometry edges (k, k+1) for every k.  Loop-closure candidates are all pairs i < j, j != i + 1,
  whose ground-truth positions are at most ``loop_closure_radius`` cells apart (default 1: the
  same vertex or an adjacent one); each candidate is kept independently with probability
  ``loop_closure_prob``.
* Edge order: odometry edges first (edge k is (k, k+1)), then loop closures in lexicographic
  (i, j) order.
* All randomness comes from ``numpy.random.default_rng(seed)`` in a fixed order (walk, loop-closure
  draws, rotation noise, translation noise), so a seed determines the dataset bit for bit.

``sigma_t = 0`` / ``sigma_R = 0`` give noise-free translations / rotations; the SE-Sync weight would
be infinite, so a unit weight is used instead (useful for exact-recovery tests).
"""

from __future__ import annotations

import functools
import math
from collections.abc import Callable
from dataclasses import dataclass
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
from jax import lax
from scipy import integrate, optimize, special

from .._core.lie import SO2, SO3, so
from .._core.pose_graph import PoseGraph, Poses
from .._core.precision import default_float_dtype, to_device

__all__ = [
    "RobotTeamDataset",
    "SyntheticDataset",
    "cube_dataset",
    "expected_edge_cost",
    "grid_2d_dataset",
    "kappa_tau_from_rmse",
    "langevin_expected_sq_angle",
    "langevin_expected_trace",
    "lattice_dataset",
    "robot_team_dataset",
    "rotation_angle",
    "sample_langevin",
]


# --------------------------------------------------------------------------------------------
# Langevin distribution on SO(d), d in {2, 3}
# --------------------------------------------------------------------------------------------


def _check_dim(dim: int) -> int:
    return so(int(dim)).dim


def max_angular_rmse(dim: int) -> float:
    """sqrt(E theta^2) under the uniform (Haar) distribution: the largest reachable sigma_R."""
    return so(_check_dim(dim)).haar_rms_angle


@functools.lru_cache(maxsize=512)
def langevin_expected_sq_angle(kappa: float, dim: int) -> float:
    """E[theta^2] for R ~ Langevin(I, kappa) on SO(dim), theta the geodesic (rotation) angle.

    Angle densities on [0, pi] (Haar measure included):
      d = 2: exp(2 kappa cos theta);  d = 3: (1 - cos theta) exp(2 kappa cos theta).
    Integrated in the scaled variable u = theta sqrt(2 kappa) so that the quadrature sees an O(1)
    bump for any kappa; the exponent is written as -4 kappa sin^2(theta/2) to avoid cancellation.
    """
    dim = _check_dim(dim)
    density = so(dim).haar_angle_density
    kappa = float(kappa)
    if kappa < 0:
        raise ValueError("kappa must be >= 0")
    if math.isinf(kappa):
        return 0.0
    if kappa == 0.0:
        return max_angular_rmse(dim) ** 2
    s = math.sqrt(2.0 * kappa)
    upper = min(math.pi * s, 60.0)  # beyond u = 60 the integrand is below exp(-700)

    def weight(u):
        th = u / s
        return math.exp(-4.0 * kappa * math.sin(0.5 * th) ** 2) * density(th)

    pts = [p for p in (1.0, 3.0, 10.0, 30.0) if p < upper]
    num = integrate.quad(lambda u: (u / s) ** 2 * weight(u), 0.0, upper, points=pts, limit=200,
                         epsabs=0.0, epsrel=1e-12)[0]
    den = integrate.quad(weight, 0.0, upper, points=pts, limit=200, epsabs=0.0, epsrel=1e-12)[0]
    return num / den


def langevin_expected_trace(kappa: float, dim: int) -> float:
    """E[tr R] for R ~ Langevin(I, kappa) on SO(dim) (closed forms with modified Bessel functions).

    d = 2: 2 I1(2k)/I0(2k).   d = 3: the normaliser is e^k (I0(2k) - I1(2k)), so
    E tr R = d/dk log c = -1 + I1(2k) / (k (I0(2k) - I1(2k))).
    """
    dim = _check_dim(dim)
    kappa = float(kappa)
    if math.isinf(kappa):
        return float(dim)
    return _LANGEVIN[so(dim)].expected_trace(kappa)


def _expected_trace_so2(kappa: float) -> float:
    x = 2.0 * kappa
    return 2.0 * special.ive(1, x) / special.ive(0, x)


def _expected_trace_so3(kappa: float) -> float:
    x = 2.0 * kappa
    if kappa < 1e-6:  # series: E tr R = kappa + O(kappa^2) (Haar mean of tr R is 0, variance 1)
        return kappa
    i0, i1 = special.ive(0, x), special.ive(1, x)
    return -1.0 + i1 / (kappa * (i0 - i1))


def expected_edge_cost(kappa, tau, dim: int):
    """E[kappa ||R^eps - I||_F^2 + tau ||t^eps||^2] for one edge at the ground truth (f = 2F).

    = 2 kappa (d - E tr R^eps) + d.  Vectorised over array-like kappa/tau (numpy result).
    Edges generated noise-free (unit weights from sigma = 0) are not covered by this formula.
    """
    dim = _check_dim(dim)
    kap = np.atleast_1d(np.asarray(kappa, dtype=np.float64))
    uniq, inv = np.unique(kap, return_inverse=True)
    rot = np.array([2.0 * k * (dim - langevin_expected_trace(k, dim)) for k in uniq])[inv]
    out = rot.reshape(kap.shape) + dim * np.ones_like(np.asarray(tau, dtype=np.float64))
    return out if np.ndim(kappa) or np.ndim(tau) else float(out.reshape(()))


def _sample_langevin_quaternions(rng: np.random.Generator, kappa: float, size: int) -> np.ndarray:
    """Bingham density exp(-4 kappa |v|^2) on S^3 (q = (v, w)), by ACG rejection (Kent et al. 2013).

    A = diag(4k, 4k, 4k, 0); envelope ACG(Omega), Omega = I + 2A/b with b solving
    sum_i 1/(b + 2 lambda_i) = 1, i.e. 1/b + 3/(b + 8k) = 1  <=>  b^2 + (8k - 4) b - 8k = 0.
    Accept x when u < exp(-x'Ax) (x'Omega x)^{q/2} / M*,  M* = exp(-(q - b)/2) (q/b)^{q/2}, q = 4.
    """
    q = 4.0
    c = 8.0 * kappa - 4.0
    disc = math.sqrt(c * c + 32.0 * kappa)
    b = 16.0 * kappa / (c + disc) if c > 0 else 0.5 * (-c + disc)  # stable root
    log_mstar = -(q - b) / 2.0 + (q / 2.0) * math.log(q / b)
    sd = math.sqrt(b / (b + 8.0 * kappa))  # Omega^{-1/2} on the vector part; 1 on w
    out = np.empty((size, 4))
    filled = 0
    while filled < size:
        batch = max(64, int(1.3 * (size - filled)) + 16)
        z = rng.standard_normal((batch, 4))
        z[:, :3] *= sd
        x = z / np.linalg.norm(z, axis=1, keepdims=True)
        v2 = np.sum(x[:, :3] ** 2, axis=1)
        log_ratio = -4.0 * kappa * v2 + (q / 2.0) * np.log1p(8.0 * kappa * v2 / b) - log_mstar
        u = rng.random(batch)
        acc = x[np.log(u) < log_ratio]
        take = min(len(acc), size - filled)
        out[filled : filled + take] = acc[:take]
        filled += take
    return out


def sample_langevin(rng: np.random.Generator, kappa: float, size: int, dim: int) -> np.ndarray:
    """``size`` i.i.d. samples of Langevin(I, kappa) on SO(dim), density exp(kappa tr R) w.r.t. Haar.

    Returns a float64 numpy array (size, dim, dim).  ``kappa = inf`` gives identities.
    """
    dim = _check_dim(dim)
    size = int(size)
    kappa = float(kappa)
    if kappa < 0:
        raise ValueError("kappa must be >= 0")
    if math.isinf(kappa):
        return np.broadcast_to(np.eye(dim), (size, dim, dim)).copy()
    return _LANGEVIN[so(dim)].sample(rng, kappa, size)


def _sample_so2(rng: np.random.Generator, kappa: float, size: int) -> np.ndarray:
    """The angle is von Mises with concentration 2 kappa (tr R = 2 cos theta, Haar: uniform angle)."""
    return SO2.exp(rng.vonmises(0.0, 2.0 * kappa, size)[:, None])


def _sample_so3(rng: np.random.Generator, kappa: float, size: int) -> np.ndarray:
    """Bingham quaternions (tr R = 4 w^2 - 1, Haar: uniform on S^3)."""
    return SO3.from_quaternion(_sample_langevin_quaternions(rng, kappa, size))


class _Langevin(NamedTuple):
    """Langevin(I, kappa) on one group: E tr R in closed form (kappa finite) and the exact sampler."""

    expected_trace: Callable[[float], float]
    sample: Callable[[np.random.Generator, float, int], np.ndarray]


_LANGEVIN = {SO2: _Langevin(_expected_trace_so2, _sample_so2), SO3: _Langevin(_expected_trace_so3, _sample_so3)}


def rotation_angle(R) -> np.ndarray:
    """Geodesic angle in [0, pi] of rotations (..., d, d), d in {2, 3} (accurate near 0)."""
    R = np.asarray(R, dtype=np.float64)
    return so(R.shape[-1]).angle(R)


@functools.lru_cache(maxsize=256)
def _kappa_from_sigma_R(sigma_R: float, dim: int) -> float:
    if sigma_R == 0.0:
        return math.inf
    smax = max_angular_rmse(dim)
    if not 0.0 < sigma_R < smax:
        raise ValueError(
            f"sigma_R must lie in (0, {smax:.6g}) for d = {dim} (the RMSE of a uniformly random "
            f"rotation), got {sigma_R}"
        )
    target = sigma_R * sigma_R
    k0 = dim * (dim - 1) / (4.0 * target)  # small-noise approximation

    def g(logk):
        return math.log(langevin_expected_sq_angle(math.exp(logk), dim)) - math.log(target)

    lo, hi = math.log(k0) - 1.0, math.log(k0) + 1.0
    while g(lo) < 0:
        lo -= 2.0
        if lo < -60:
            return 0.0
    while g(hi) > 0:
        hi += 2.0
    return math.exp(optimize.brentq(g, lo, hi, xtol=1e-14, rtol=1e-13))


def kappa_tau_from_rmse(sigma_t: float, sigma_R: float, dim: int) -> tuple[float, float]:
    """(kappa, tau) giving expected translational RMSE ``sigma_t`` and angular RMSE ``sigma_R``.

    tau = d / sigma_t^2 (E ||t^eps||^2 = d / tau); kappa solves E theta^2 = sigma_R^2 under
    Langevin(I, kappa) (see the module docstring).  A zero sigma gives an infinite weight.
    """
    dim = _check_dim(dim)
    sigma_t, sigma_R = float(sigma_t), float(sigma_R)
    if sigma_t < 0 or sigma_R < 0:
        raise ValueError("noise levels must be >= 0")
    tau = math.inf if sigma_t == 0.0 else dim / sigma_t**2
    return _kappa_from_sigma_R(sigma_R, dim), tau


# --------------------------------------------------------------------------------------------
# Datasets
# --------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class SyntheticDataset:
    """A generated pose graph with its ground truth and the noise levels that produced it."""

    name: str
    graph: PoseGraph
    ground_truth: Poses
    sigma_t: float
    sigma_R: float
    seed: int

    @property
    def dim(self) -> int:
        return self.graph.dim

    @property
    def num_poses(self) -> int:
        return self.graph.num_poses

    @property
    def num_edges(self) -> int:
        return self.graph.num_edges

    @property
    def num_odometry_edges(self) -> int:
        """Edges 0 .. n-2 are the odometry edges (k, k+1); the rest are loop closures."""
        return self.graph.num_poses - 1

    @property
    def kappa(self) -> float:
        return float(self.graph.kappa[0])

    @property
    def tau(self) -> float:
        return float(self.graph.tau[0])

    def expected_ground_truth_cost(self) -> float:
        """E[f(ground truth)] (f = 2F) under the generative model; 0 for noise-free data."""
        if self.sigma_t == 0.0 and self.sigma_R == 0.0:
            return 0.0
        kap, _tau = kappa_tau_from_rmse(self.sigma_t, self.sigma_R, self.dim)
        per_edge = (0.0 if self.sigma_R == 0.0 else expected_edge_cost(kap, 1.0, self.dim) - self.dim)
        per_edge += 0.0 if self.sigma_t == 0.0 else self.dim
        return float(self.num_edges * per_edge)


def _plane_rotations(h_from: np.ndarray, h_to: np.ndarray) -> np.ndarray:
    """The rotations (k, d, d) taking unit vectors h_from[k] to h_to[k] (orthogonal, equal or
    opposite), fixing the rest.

    Orthogonal: the 90-degree rotation in span{h_from, h_to}:
        Q = I - a a' - b b' + b a' - a b'.
    Opposite: a pi rotation in the plane of h_from and the first coordinate axis orthogonal to it.
    """
    k, d = h_from.shape
    a, b = h_from[:, :, None], h_to[:, :, None]
    at, bt = h_from[:, None, :], h_to[:, None, :]
    eye = np.eye(d)
    turn = eye - a * at - b * bt + b * at - a * bt
    c = np.zeros((k, d))
    c[np.arange(k), np.argmax(np.abs(h_from) < 0.5, axis=1)] = 1.0
    flip = eye - 2.0 * (a * at) - 2.0 * (c[:, :, None] * c[:, None, :])
    dot = np.einsum("ka,ka->k", h_from, h_to)[:, None, None]
    return np.where(dot < -0.5, flip, np.where(dot > 0.5, eye, turn))


@functools.partial(jax.jit, static_argnums=(1, 2, 3))
def _walk_moves(u: jax.Array, dim: int, grid: int, length: int, num_steps, num_draws):
    """The moves (length,) of the walk from the 32-bit draws ``u[:num_draws]``, and how many draws
    it used; steps from ``num_steps`` on (padding: ``length`` is a power of two, so that one
    compilation serves every walk up to it) neither move nor draw.

    Move s < dim is +1 along axis s, move s >= dim is -1 along axis s - dim. A step with k > 1
    options takes numpy's ``rng.integers(k)`` from the draws (Lemire's method: from a draw x,
    m = x k in 64 bits; draw again while the low 32 bits of m are below (2^32 - k) mod k; the
    option is m >> 32); a step with one option draws nothing. The walk is a Markov chain on
    (vertex, last move), so the steps run one after another, inside a compiled scan.
    """
    two_d = 2 * dim
    s = jnp.arange(two_d, dtype=jnp.int32)
    axis, sign = s % dim, jnp.where(s < dim, 1, -1).astype(jnp.int32)
    last = num_draws - 1

    def bounded(used, k):  # numpy's rng.integers(k) from u[used:], and the draws it consumed
        k = k.astype(jnp.uint32)
        threshold = (jnp.uint32(0) - k) % k
        used = lax.while_loop(lambda i: (u[jnp.minimum(i, last)] * k < threshold) & (i <= last),
                              lambda i: i + 1, used)
        x = u[jnp.minimum(used, last)]
        high = ((x >> 16) * k + (((x & 0xFFFF) * k) >> 16)) >> 16  # (x k) >> 32 in 32-bit words
        return high.astype(jnp.int32), used + 1

    def step(carry, k):
        pos, prev, used = carry
        nxt = pos[axis] + sign
        ok = (nxt >= 0) & (nxt <= grid)
        ok_forward = ok & (s != (prev + dim) % two_d)
        ok = jnp.where((prev >= 0) & ok_forward.any(), ok_forward, ok)
        n_ok = ok.sum()
        draws = (n_ok > 1) & (k < num_steps)
        choice, used_after = bounded(used, jnp.maximum(n_ok, 2))
        choice = jnp.where(draws, choice, 0)
        used = jnp.where(draws, used_after, used)
        move = jnp.argmax(jnp.cumsum(ok) == choice + 1).astype(jnp.int32)
        pos = pos.at[move % dim].add(jnp.where(k < num_steps, jnp.where(move < dim, 1, -1), 0))
        return (pos, move, used), move

    start = (jnp.zeros(dim, jnp.int32), jnp.int32(-1), jnp.int32(0))
    (_, _, used), moves = lax.scan(step, start, jnp.arange(length, dtype=jnp.int32))
    return moves, used


def _lattice_walk(rng: np.random.Generator, dim: int, grid: int, num_poses: int) -> np.ndarray:
    """Integer vertex coordinates (num_poses, dim) of the non-reversing random walk.

    Bit for bit one ``rng.integers(len(options))`` call per step with more than one option (the
    definition the tests check against): the 32-bit draws are made at once
    (``rng.integers(0, 2**32, dtype=uint32)`` is the same stream numpy's bounded draws consume),
    the steps run in :func:`_walk_moves`, and the generator is then left exactly where the
    per-step calls would leave it. The positions are a cumulative sum of the moves.
    """
    if num_poses < 2:
        return np.zeros((num_poses, dim), dtype=np.int64)
    steps = num_poses - 1
    length = max(256, 1 << (steps - 1).bit_length())  # the compiled walk's size: the next power of two
    saved = rng.bit_generator.state
    spare = 16
    while True:  # a redraw has probability <= 2^-32 per step: the spare draws almost always do
        u = rng.integers(0, 2**32, size=steps + spare, dtype=np.uint32)
        padded = np.zeros(length + spare, np.uint32)
        padded[: u.size] = u
        moves, used = _walk_moves(jax.device_put(padded), dim, grid, length, steps, u.size)
        used = int(used)
        rng.bit_generator.state = saved
        if used <= u.size:
            break
        spare *= 16
    rng.integers(0, 2**32, size=used, dtype=np.uint32)  # consume exactly the draws used
    unit = np.concatenate([np.eye(dim, dtype=np.int64), -np.eye(dim, dtype=np.int64)])
    return np.concatenate([np.zeros((1, dim), np.int64), np.cumsum(unit[np.asarray(moves)[:steps]], axis=0)])


def _heading_frames(pos: np.ndarray) -> np.ndarray:
    """Rotations whose first axis is the heading of travel, carried by parallel transport.

    R_0 = Q(e_1, h_0) and R_k = Q(h_{k-1}, h_k) R_{k-1}: the prefix products are formed by
    doubling (ceil(log2 n) batched matmuls). All factors are signed permutation matrices, so every
    product is exact and the association order does not change a bit.
    """
    n, d = pos.shape
    if n == 1:
        return np.eye(d)[None].copy()
    heads = np.diff(pos, axis=0).astype(np.float64)  # (n-1, d) unit axis vectors
    heads = np.concatenate([heads, heads[-1:]], 0)  # last pose keeps its arrival heading
    e1 = np.zeros((1, d))
    e1[0, 0] = 1.0
    R = _plane_rotations(np.concatenate([e1, heads[:-1]]), heads)  # R[k] = Q_k; Q_0 = Q(e1, h_0)
    span = 1
    while span < n:  # R[k] <- R[k] R[k - span]: after the pass, R[k] = Q_k ... Q_{max(0, k-2 span+1)}
        R[span:] = R[span:] @ R[:-span]
        span *= 2
    return R


def _loop_closure_candidates(pos: np.ndarray, radius: float) -> np.ndarray:
    """All pairs (i, j), i < j, j != i+1, with |pos_i - pos_j| <= radius (lattice units), sorted."""
    from scipy.spatial import cKDTree

    if len(pos) < 3 or radius < 0:
        return np.zeros((0, 2), dtype=np.int64)
    pairs = cKDTree(pos.astype(np.float64)).query_pairs(r=radius + 1e-9, output_type="ndarray")
    pairs = np.sort(pairs.astype(np.int64), axis=1)
    pairs = pairs[pairs[:, 1] != pairs[:, 0] + 1]
    order = np.lexsort((pairs[:, 1], pairs[:, 0]))
    return pairs[order]


def lattice_dataset(
    seed: int = 0,
    *,
    dim: int,
    grid: int,
    side: float = 1.0,
    num_poses: int,
    loop_closure_prob: float = 0.1,
    loop_closure_radius: float = 1.0,
    sigma_t: float = 0.02,
    sigma_R: float = 0.02 * np.pi,
    dtype=None,
    name: str | None = None,
) -> SyntheticDataset:
    """A random walk on a ``grid``^dim lattice with noisy odometry and loop closures.

    See the module docstring for the path and noise model.  :func:`cube_dataset` and
    :func:`grid_2d_dataset` are the 3D and 2D presets.
    """
    dim = _check_dim(dim)
    grid, num_poses, seed = int(grid), int(num_poses), int(seed)
    if grid < 1:
        raise ValueError("grid must be >= 1")
    if num_poses < 2:
        raise ValueError("num_poses must be >= 2")
    if not 0.0 <= loop_closure_prob <= 1.0:
        raise ValueError("loop_closure_prob must lie in [0, 1]")
    kappa, tau = kappa_tau_from_rmse(sigma_t, sigma_R, dim)
    rng = np.random.default_rng(seed)

    pos = _lattice_walk(rng, dim, grid, num_poses)
    Rgt = _heading_frames(pos)
    tgt = side * pos.astype(np.float64)

    cand = _loop_closure_candidates(pos, loop_closure_radius)
    keep = rng.random(len(cand)) < loop_closure_prob
    odo = np.stack([np.arange(num_poses - 1), np.arange(1, num_poses)], 1)
    edges = np.concatenate([odo, cand[keep]], 0)
    I, J = edges[:, 0], edges[:, 1]
    m = len(I)

    Rrel = np.swapaxes(Rgt[I], 1, 2) @ Rgt[J]
    trel = np.einsum("mba,mb->ma", Rgt[I], tgt[J] - tgt[I])
    Rn = sample_langevin(rng, kappa, m, dim)  # identities when sigma_R = 0
    tn = np.zeros((m, dim)) if math.isinf(tau) else rng.standard_normal((m, dim)) / math.sqrt(tau)
    Rmeas = Rrel @ Rn
    tmeas = trel + tn

    kap_w = 1.0 if math.isinf(kappa) else kappa
    tau_w = 1.0 if math.isinf(tau) else tau
    graph = PoseGraph.from_arrays(
        I, J, Rmeas, tmeas, np.full(m, kap_w), np.full(m, tau_w), num_poses=num_poses, dtype=dtype
    )
    fdt = np.dtype(dtype or default_float_dtype())
    gt = Poses(to_device(Rgt, fdt), to_device(tgt, fdt))
    if name is None:
        name = f"{_PRESET_NAME[so(dim)]}_seed{seed}"
    return SyntheticDataset(name=name, graph=graph, ground_truth=gt, sigma_t=float(sigma_t),
                            sigma_R=float(sigma_R), seed=seed)


#: the default dataset name of each group's lattice (that of its preset below)
_PRESET_NAME = {SO2: "grid2d", SO3: "cube"}


def cube_dataset(
    seed: int = 0,
    *,
    grid: int = 12,
    side: float = 1.0,
    num_poses: int = 3600,
    loop_closure_prob: float = 0.1,
    sigma_t: float = 0.02,
    sigma_R: float = 0.02 * np.pi,
    dtype=None,
    loop_closure_radius: float = 1.0,
) -> SyntheticDataset:
    """The paper's Cube dataset (Fig. 1, docs/conventions.md §8): 12x12x12 cells of 1 m, 3600 poses,
    loop-closure probability 0.1, sigma_t = 0.02 m, sigma_R = 0.02 pi rad.  Deterministic in seed.
    """
    return lattice_dataset(seed, dim=3, grid=grid, side=side, num_poses=num_poses,
                           loop_closure_prob=loop_closure_prob,
                           loop_closure_radius=loop_closure_radius, sigma_t=sigma_t,
                           sigma_R=sigma_R, dtype=dtype, name=f"cube_seed{int(seed)}")


def grid_2d_dataset(
    seed: int = 0,
    *,
    grid: int = 20,
    side: float = 1.0,
    num_poses: int = 1000,
    loop_closure_prob: float = 0.1,
    sigma_t: float = 0.02,
    sigma_R: float = 0.02 * np.pi,
    dtype=None,
    loop_closure_radius: float = 1.0,
) -> SyntheticDataset:
    """Planar counterpart of :func:`cube_dataset` on a ``grid`` x ``grid`` lattice."""
    return lattice_dataset(seed, dim=2, grid=grid, side=side, num_poses=num_poses,
                           loop_closure_prob=loop_closure_prob,
                           loop_closure_radius=loop_closure_radius, sigma_t=sigma_t,
                           sigma_R=sigma_R, dtype=dtype, name=f"grid2d_seed{int(seed)}")


# --------------------------------------------------------------------------------------------
# Robot teams: long odometry chains with few loop closures
# --------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class RobotTeamDataset(SyntheticDataset):
    """A :func:`robot_team_dataset`: ``robot_of_pose`` (n,) (robot r owns poses r P .. r P + P - 1)
    and the (m,) edge kinds (``odometry``, ``intra_robot`` loop closures, ``inter_robot`` ones)."""

    robot_of_pose: np.ndarray = None
    edge_kind: np.ndarray = None  # (m,) 0 odometry, 1 intra-robot loop closure, 2 inter-robot loop closure

    @property
    def num_odometry_edges(self) -> int:
        return int((self.edge_kind == 0).sum())

    @property
    def inter_robot(self) -> np.ndarray:
        return self.edge_kind == 2


def _team_walk(rng: np.random.Generator, dim: int, grid: int, num_poses: int) -> np.ndarray:
    """The lattice walk from the origin corner, moved to a random corner and axis order (a mirror
    or permutation of the lattice), so that the robots start apart and cross each other's paths."""
    pos = _lattice_walk(rng, dim, grid, num_poses)
    flip = rng.random(dim) < 0.5
    pos = np.where(flip, grid - pos, pos)
    return pos[:, rng.permutation(dim)]


def _pick(rng: np.random.Generator, pairs: np.ndarray, count: int) -> np.ndarray:
    """``count`` of ``pairs`` (all when fewer), uniformly without replacement, in (i, j) order."""
    if count >= len(pairs):
        return pairs
    chosen = pairs[np.sort(rng.choice(len(pairs), size=count, replace=False))]
    return chosen


def _inter_candidates(pos: np.ndarray, rop: np.ndarray, radius: float) -> np.ndarray:
    """Pairs (i, j), i < j, of poses of different robots at most ``radius`` cells apart."""
    from scipy.spatial import cKDTree

    pairs = cKDTree(pos.astype(np.float64)).query_pairs(r=radius + 1e-9, output_type="ndarray").astype(np.int64)
    pairs = np.sort(pairs, axis=1)
    pairs = pairs[rop[pairs[:, 0]] != rop[pairs[:, 1]]]
    return pairs[np.lexsort((pairs[:, 1], pairs[:, 0]))]


def _connecting_closures(rng: np.random.Generator, cand: np.ndarray, rop: np.ndarray, robots: int) -> np.ndarray:
    """One candidate closure per robot joining it to an earlier robot of a random order (a random
    spanning tree of the robots), so that the team's graph is connected; fewer where no candidate
    joins a robot to the others."""
    ra, rb = rop[cand[:, 0]], rop[cand[:, 1]]
    order = rng.permutation(robots)
    joined = np.zeros(robots, bool)
    joined[order[0]] = True
    chosen = []
    for r in order[1:]:  # robots, not poses: at most ``robots`` rounds
        ok = np.flatnonzero(((ra == r) & joined[rb]) | ((rb == r) & joined[ra]))
        if len(ok):
            chosen.append(int(ok[rng.integers(len(ok))]))
            joined[r] = True
    return np.asarray(chosen, np.int64)


_TEAM_GRID_CAP = {2: 20, 3: 12}  # lattice sides at most: 400 cells in 2D, 1728 in 3D


def robot_team_dataset(
    robots: int = 10,
    poses_per_robot: int = 1500,
    *,
    intra_closures: int = 10,
    inter_closures: int = 40,
    dim: int = 2,
    seed: int = 0,
    grid: int | None = None,
    side: float = 1.0,
    sigma_t: float = 0.02,
    sigma_R: float = 0.02 * np.pi,
    loop_closure_radius: float = 1.0,
    dtype=None,
) -> RobotTeamDataset:
    """A team of ``robots`` robots, each a long odometry chain with few loop closures: the case of
    multi-robot SLAM where the robots' maps are tied together by a handful of inter-robot closures
    and each chain drifts far between them (the Cube datasets' noise and walk, one walk per robot).

    Robot r walks ``poses_per_robot`` poses (P) on the shared ``grid``^dim lattice (default
    min(20, sqrt P) cells in 2D, min(12, P^(1/3)) in 3D), from a random corner
    (:func:`_team_walk`); it has odometry edges only along its own chain (no edge joins the last
    pose of one robot to the first of the next). Loop-closure candidates are pose pairs at most
    ``loop_closure_radius`` cells apart (as in :func:`lattice_dataset`); each robot gets
    ``intra_closures`` of its own, drawn uniformly, and the team ``inter_closures`` between
    robots: first one per robot along a random spanning tree of the robots (so that the graph is
    connected; ValueError when some robot never meets the others), the rest uniformly.
    Measurements and weights as in :func:`lattice_dataset` (sigma_t, sigma_R). Edge order: each
    robot's odometry, then the intra-robot closures, then the inter-robot ones. Deterministic in
    ``seed``.
    """
    dim = _check_dim(dim)
    robots, poses_per_robot, seed = int(robots), int(poses_per_robot), int(seed)
    if robots < 1 or poses_per_robot < 2:
        raise ValueError("robot_team_dataset needs robots >= 1 and poses_per_robot >= 2")
    if int(intra_closures) < 0 or int(inter_closures) < 0:
        raise ValueError("intra_closures and inter_closures must be >= 0")
    if grid is None:  # a lattice each walk covers a good part of, so that the robots meet
        grid = min(_TEAM_GRID_CAP[dim], max(2, round(poses_per_robot ** (1 / dim))))
    grid = int(grid)
    kappa, tau = kappa_tau_from_rmse(sigma_t, sigma_R, dim)
    rng = np.random.default_rng(seed)
    P = poses_per_robot
    n = robots * P
    rop = np.repeat(np.arange(robots), P)
    walks = [_team_walk(rng, dim, grid, P) for _ in range(robots)]
    pos = np.concatenate(walks)
    Rgt = np.concatenate([_heading_frames(w) for w in walks])
    tgt = side * pos.astype(np.float64)

    odo = np.stack([np.arange(n - 1), np.arange(1, n)], 1)
    odo = odo[rop[odo[:, 0]] == rop[odo[:, 1]]]
    intra = [r * P + _pick(rng, _loop_closure_candidates(w, loop_closure_radius), int(intra_closures))
             for r, w in enumerate(walks)]
    intra = np.concatenate(intra).reshape(-1, 2)
    cand = _inter_candidates(pos, rop, loop_closure_radius)
    tree = _connecting_closures(rng, cand, rop, robots)
    if len(tree) < robots - 1:
        raise ValueError(f"robot_team_dataset: some robots' walks never come within {loop_closure_radius} cells of "
                         f"the others' (seed {seed}): use a smaller grid or more poses_per_robot")
    rest = np.setdiff1d(np.arange(len(cand)), tree)
    extra = _pick(rng, rest[:, None], max(0, int(inter_closures) - len(tree)))[:, 0]
    inter = cand[np.sort(np.concatenate([tree, extra]))]
    edges = np.concatenate([odo, intra, inter]).astype(np.int64)
    kind = np.repeat([0, 1, 2], [len(odo), len(intra), len(inter)])
    I, J = edges[:, 0], edges[:, 1]
    m = len(I)

    Rrel = np.swapaxes(Rgt[I], 1, 2) @ Rgt[J]
    trel = np.einsum("mba,mb->ma", Rgt[I], tgt[J] - tgt[I])
    Rn = sample_langevin(rng, kappa, m, dim)
    tn = np.zeros((m, dim)) if math.isinf(tau) else rng.standard_normal((m, dim)) / math.sqrt(tau)
    kap_w = 1.0 if math.isinf(kappa) else kappa
    tau_w = 1.0 if math.isinf(tau) else tau
    graph = PoseGraph.from_arrays(I, J, Rrel @ Rn, trel + tn, np.full(m, kap_w), np.full(m, tau_w),
                                  num_poses=n, dtype=dtype)
    fdt = np.dtype(dtype or default_float_dtype())
    gt = Poses(to_device(Rgt, fdt), to_device(tgt, fdt))
    return RobotTeamDataset(name=f"team{robots}x{P}_{dim}d_seed{seed}", graph=graph, ground_truth=gt,
                            sigma_t=float(sigma_t), sigma_R=float(sigma_R), seed=seed, robot_of_pose=rop,
                            edge_kind=kind)
