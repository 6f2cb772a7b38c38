"""Distributed chordal initialization (paper §VII): two linear least-squares stages, each solved
with only neighbour exchanges, by one of two schemes on the same per-robot matrices Gamma^alpha:

* ``scheme="cg"`` (default): preconditioned conjugate gradients (:class:`CGChordal`) with the
  robots' Gamma^alpha as a block-Jacobi preconditioner (section "Conjugate gradients" below);
* ``scheme="amm"``: the paper's accelerated majorization minimization, Algorithm 3
  (:class:`AMMChordal`), described first.

Rotations (Algorithm 3, "AMM-Chordal"). The relaxed problem (22) min F_R(R) over R in
R^{d x dn} with R_0 = I is split among the robots of a :class:`~mmpgo_jax._core.partition.Partition`. Eq. (24)
majorizes every inter-robot term 1/2 kappa ||R_i Rt - R_j||^2 by kappa ||R_i Rt - P||^2 +
kappa ||R_j - P||^2 around the midpoint P of the current iterate, plus a proximal term
xi/2 ||R - R^k||^2. As a function of robot alpha's own blocks the majorizer is the quadratic

    G_R^alpha(Z | Y) = 1/2 <Gamma_R^alpha (Z - Y), Z - Y> + <grad_alpha F_R(Y), Z - Y> + const,

    Gamma_R^alpha = (kappa-connection Laplacian of the robot's own edges)
                    + sum over its inter-robot edges of 2 kappa Rt Rt^T (tail) or 2 kappa I (head)
                      on the local pose's diagonal block
                    + xi I,

which is constant over the iterations. Its exact minimiser is Z = Y - grad_alpha F_R(Y)
(Gamma_R^alpha)^{-1} (acting from the right on the d x dn block row). Algorithm 3 adds
Nesterov momentum: s_{k+1} = (sqrt(4 s_k^2 + 1) + 1) / 2, gamma_k = (s_k - 1) / s_{k+1},
Y^k = R^k + gamma_k (R^k - R^{k-1}) and, since grad F_R is affine,
grad F_R(Y^k) = grad F_R(R^k) + gamma_k (grad F_R(R^k) - grad F_R(R^{k-1})) exactly (line 13),
so each iteration evaluates one gradient (at the new iterate) and exchanges each robot's poses at
the ends of its inter-robot edges once.

Translations. With the projected rotations fixed, the translation problem (25)-(26) is the same
kind of quadratic with the tau-weighted graph Laplacian (a scalar n_alpha x n_alpha Gamma_t^alpha,
2 tau on inter-robot edge ends, + xi I), solved by the identical accelerated scheme, t_0 = 0.

Anchoring. As in the centralized version (:func:`~mmpgo_jax._core.gauge.anchor_set`) the fixed poses
(g2o FIX) are held at their values and the first pose of every other connected component of the
measurement graph at R = I, t = 0 (pose 0 of robot 0 for a connected graph without fixed poses
and the contiguous partition). An anchor is eliminated from the robot's
subproblem by zeroing its gradient and its rows/columns of Gamma (identity on the diagonal), so
its value never moves.

Solves (the dense inverses; "Factorization" below for the sparse factors that large robots use).
Gamma^alpha is factored once, on the host: all robots' Gamma are assembled densely by one
scatter of the edge blocks (n_max slots, identity on padding slots and anchor rows/columns) and
each is inverted from its Cholesky factor (LAPACK potrf, trtri, lauum; on this machine 5-10x faster
than a sparse LU solved against the identity, e.g. 0.28 s vs 1.6 s for one torus3D robot,
N = 1500), with the entries below eps^2 of the largest set to zero between the steps: these inverses
decay along the graph, and the products of their tiny entries are subnormal numbers that the CPU
computes slowly (city10000, 10 robots: 2.0 s -> 0.6-0.8 s; :func:`_invert_in_place`). The iteration
then applies all robots' inverses by one batched matrix product, (A, N, N) x (A, N, d) with N = n_max d
(rotations) or n_max (translations). Measured on this 2-core CPU for A = 10, N = 2000, d = 2
right-hand sides: batched product 29-34 ms per application, vmapped
``jax.scipy.linalg.cho_solve`` with the dense Cholesky factor 840 ms (XLA's CPU triangular solve
is not blocked for few right-hand sides), so the explicit inverse is used (a sparse factorization
is applied on the host instead, "Factorization"). The product is
memory-bound: A N^2 float64 are read per iteration (320 MB for city10000 with 10 robots, which
is also the memory held). Structure is not exploited beyond that: for d = 2 the blocks are
complex numbers (half the bytes; measured only 1.3-1.5x faster), and for city10000 ~85% of the
poses touch an inter-robot edge, so a Schur complement onto the interface poses would not pay.
Planar rotations (d = 2): every 2 x 2 block of Gamma_R^alpha is a scaled rotation [[a, -b], [b, a]],
i.e. the complex number a + i b acting on the rows of R^T read as complex numbers, and so is every
block of its inverse: the inverse is computed as a complex n_max x n_max Hermitian matrix (complex
LAPACK) and stored as its real and imaginary parts, applied with two real products of half the
bytes of the real 2 n_max x 2 n_max inverse (city10000, 10 robots, CG: 3.9 ms per rotation
iteration against 7.1, set-up 0.5 s against 1.1; used when every measured rotation is planar).

Factorization (``factorization``, default ``"auto"``). The dense inverses above cost A N^3 to
build and A N^2 to read at every iteration, which grows with the robots' size; so each robot's
Gamma^alpha can instead be factored sparse, once, on the host (SuperLU through
:func:`scipy.sparse.linalg.splu`, symmetric fill-reducing ordering, diagonal pivots: one
factorization of the block-diagonal matrix of all robots, i.e. each robot's own; complex for planar
rotations as above), and applied from inside the compiled iteration by one host callback per
iteration for all robots (``jax.pure_callback``: the triangular solves, O(nnz of the factors)).
``"auto"`` takes the sparse factors on the CPU for a stage whose dense inverses (the bytes one
iteration reads, in the precision they get: float32 or, by the rule below, float64) exceed the
largest CPU cache, where the dense product streams them from memory at
every iteration, and on any backend where the dense inverses would not fit in memory (instead of
refusing). Below that size the dense product runs from the cache, faster than the callback and the
triangular solves. Measured on a 2-core AMD EPYC (Zen 4, 32 MB L3; benchmarks/vs_authors.md), in the
process, 10 robots, dense -> sparse: city10000 3.7-4.7 -> 1.9-2.7 s, the 15 000-pose chain graph
6.2-7.4 -> 2.5-3.1 s, torus3D 1.2 -> 0.6-0.7 s (dense inverses of 80-270 MB; their set-up alone
0.5-2.5 s, the sparse factorization 0.02-0.05 s), parking-garage 0.7 -> 1.2-1.4 s and MIT 0.04 -> 0.10 s
(inverses of 0.1-10 MB, which "auto" keeps dense: an empty callback costs 65-100 us, SuperLU's
solves with few columns run at about 1 GFLOP/s). The two give the same iteration counts on those
files (the float32 rule below aside). A program with a host callback is not kept in the persistent
compilation cache, so a sparse stage compiles in every process (about 0.5-0.7 s for both stages'
programs here), which the whole process still recovers on those three graphs.

Momentum restart (``restart=True``, the default). Algorithm 3's momentum never restarts; on
these strongly convex but badly conditioned quadratics plain Nesterov momentum oscillates (the
objective is not monotone) and converges slowly. With ``restart`` each robot alpha resets its own
s^alpha to 1 when its step goes uphill, <grad_alpha F(Y^k), R^{alpha(k+1)} - R^{alpha(k)}> > 0
(the gradient restart of O'Donoghue & Candes, 2015). The test uses only the robot's own
quantities, so it costs no computation or communication; lines 11-14 of Algorithm 3 are
unchanged otherwise, and ``restart=False`` is Algorithm 3 verbatim. Measured with 10 robots
(iterations until the relaxed rotation objective stays within 1e-6 of the centralized one):
MIT 825 -> 301, CSAIL > 3000 -> 494, intel > 3000 -> 1875, sphere2500 781 -> 199,
torus3D 360 -> 109, city10000 > 3000 -> 964; see benchmarks/initialization.md.

Conjugate gradients (the default). Both stages minimise a convex quadratic, 1/2 <X, H X> - <B, X>
per column (d independent right-hand sides: the columns of the stacked R^T, or of t), so
conjugate gradients apply, preconditioned by the same Gamma^alpha (block Jacobi over the robots:
each robot's own-edge block, with its inter-robot diagonal terms doubled; the exact diagonal blocks
were measured to need the same iterations). An iteration costs what an AMM-Chordal iteration costs
(H applied to the search direction: one exchange of each robot's poses at its inter-robot edge ends;
one product with every robot's Gamma^{-1}) plus two sums over all robots of d numbers (the step length
and the conjugacy coefficient of each column), an all-reduce AMM-Chordal does not need. CG's error
after k iterations falls like ((sqrt(c) - 1) / (sqrt(c) + 1))^k in the condition number c of
Gamma^{-1} H, the rate momentum methods only approach. Measured with 10 robots, iterations to a
relative 1e-6 of the relaxed rotation optimum (benchmarks/initialization.md): MIT 45 against 301
with restarted AMM-Chordal, intel 238 against 1875. The objective is updated exactly along each
step (f(X + a p) = f(X) - 2a <r, p> + a^2 <p, H p>), so it is non-increasing, and the driver's
stopping rule below applies unchanged. Polak-Ribiere's conjugacy coefficient (flexible CG)
is used: equal to the classical one with an exact symmetric preconditioner, and robust to a
slightly inexact one.

Preconditioner precision. CG only needs Gamma^{-1} as a preconditioner, so its inverses are
factored and stored in float32 (half the bytes every iteration reads, the iteration being
memory-bound; the factorization is about 2.5x faster) while the iterates, residuals and objective
stay in the graph's precision. A float32 inverse is off by about kappa(Gamma^alpha) u (u = 6e-8,
float32's unit roundoff), and CG's fast final phase is sensitive to it: kitti_00 (10 robots, kappa u
0.35 for rotations, 0.020 for translations, LAPACK's estimate) took 470 / 440 CG iterations with
float32 inverses against 210 / 240 with float64 ones, the same start. So float32 is used only where
every robot's kappa u, from LAPACK's condition estimate of the float32 Cholesky factor (``pocon``,
1-norm, O(N^2) beside the O(N^3) factorization), is at most ``SINGLE_PRECISION_ERROR`` = 0.01 (the
preconditioner within 1 % of the exact one); otherwise, or where a float32 factorization fails, all
inverses are float64. On the other benchmark files kappa u is 1e-5 to 0.023 and float32 costs no
iterations (the counts agree within a chunk: e.g. CSAIL 8.4e-3, the chain graph's translations 0.023
and manhattan's rotations 0.012, the last two now float64 by the rule, which errs towards float64).
AMM-Chordal's inverse is its majorizer's exact minimiser, always in the graph's precision.

Convergence of AMM-Chordal. The iteration count is governed by lambda_min(Gamma^{-1} L) of the anchored
problem; the slowest mode is the "gauge" mode (all free poses left-multiplied by a common matrix,
held back only by the edges at the single anchor pose): for intel lambda_min = 2e-5 with the
eigenvector 99.7% inside that mode, for parking-garage 3.6e-6 (98%). A one-matrix global
correction of that mode per iteration was tried and did not help (the next modes are almost as
slow), so it is not included.

Proximal weight ``xi`` (default 1e-3, in the units of kappa and tau). It makes Gamma^alpha
positive definite whatever the graph (e.g. zero-weight edges); with the component anchoring
Gamma^alpha is already positive definite for xi = 0 on connected data. It is negligible next to
the measurement weights of the benchmark files: it slows the majorizer by a relative xi /
(weights at a pose), and xi = 0 and 1e-3 give the same iteration counts there.

Stopping. Each stage is a solver (:class:`CGChordal` or :class:`AMMChordal`) run by the same driver as MM and AMM
(:func:`~mmpgo_jax._mm.driver.drive`): compiled chunks of 10 iterations, the budget, and
``tol`` (relative, default 1e-10; None runs the whole budget) as the driver's relative-change
rule, checked after every chunk: a stage stops after the first chunk (k = 10, 20, ...) with
|f(X^{k-10}) - f(X^k)| <= tol * f(X^k) (an increase is not convergence), f the relaxed objective
(which every iteration computes anyway from the residuals of the gradient evaluation: each robot
sums its own edges and half of its inter-robot edges; CG updates it along each step). With the
momentum restart the objective decreases essentially monotonically and linearly, and on the
benchmark files the gap to the optimum at the stop was within 1-100x of tol; CG's relaxed rotation
gap at the stop was 5e-13 to 2.4e-9 (parking-garage). ``tol`` and the budget are traced values:
the one compiled chunk of a graph shape serves every tolerance and budget. The rotation stage's
output is projected to SO(d) block by block, which multiplies a block's error by the inverse of its
smallest singular value sigma: where the relaxation collapses (long noisy chains, sigma down to
2e-8; the benchmark files 0.013-0.99) the relaxed objective settles to 11 digits while the projected
rotations are still off by radians. So a rotation stage stopped by ``tol`` goes on (the same CG, its
state kept) until its residual is within sqrt(tol) sigma of the first (:func:`_projection_settled`);
no benchmark file needs it, and a 15 000-pose chain graph's start went from +500 % of the
centralized chordal start's f to +0.36 % (160 -> 250 rotation iterations).

Budgets. The defaults (20000 + 20000 iterations) are a cap, not a cost: every benchmark file
stops by ``tol`` first. With CG the files need 60-470 iterations per stage; AMM-Chordal needs
thousands on the ill-conditioned ones (parking-garage about 6400 + 7700, intel about 2700 + 3000;
with budgets of 2000 they stopped far from the solution), benchmarks/initialization.md.
"""

from __future__ import annotations

import contextlib
import dataclasses
from dataclasses import dataclass
from typing import ClassVar

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import scipy.linalg as sla
import scipy.sparse as sp
import scipy.sparse.linalg as spla

from .._core.gauge import FixedPoses, anchor_set
from .._core.geometry import bmm, mT, project_to_so
from .._core.partition import Partition
from .._core.partition import partition as make_partition
from .._core.pose_graph import PoseGraph, Poses, edge_hessian_blocks
from .._core.resources import available_memory_bytes, last_level_cache_bytes
from .._core.validate import check_count, check_real
from .._mm.driver import RESULTS, Termination, compile_once, drive
from .._mm.layouts import Placement
from .._mm.outer import IterationRecord
from .._mm.solvers import Solver, start_run

__all__ = [
    "DEFAULT_FACTORIZATION",
    "DEFAULT_ROTATION_ITERATIONS",
    "DEFAULT_SCHEME",
    "DEFAULT_TOL",
    "DEFAULT_TRANSLATION_ITERATIONS",
    "DEFAULT_XI",
    "FACTORIZATIONS",
    "AMMChordal",
    "CGChordal",
    "DistributedChordalInfo",
    "distributed_chordal_initialization",
    "distributed_relaxed_rotations",
    "distributed_translations",
]

DEFAULT_ROTATION_ITERATIONS = 20000
DEFAULT_TRANSLATION_ITERATIONS = 20000
DEFAULT_TOL = 1e-10
DEFAULT_XI = 1e-3
DEFAULT_RESTART = True
DEFAULT_SCHEME = "cg"
DEFAULT_FACTORIZATION = "auto"
SINGLE_PRECISION_ERROR = 0.01  # the float32 preconditioner's largest relative error, kappa u (module docstring)
FACTORIZATIONS = ("auto", "dense", "sparse")
_CHUNK = 10  # iterations per compiled chunk between the driver's convergence checks


# --------------------------------------------------------------------------------------------
# host-side set-up: Gamma^alpha and its inverse
# --------------------------------------------------------------------------------------------


def _padded_anchor_mask(part: Partition, anchors: np.ndarray) -> np.ndarray:
    mask = np.zeros(part.pose_mask.shape, dtype=bool)
    rob = np.asarray(part.robot_of_pose)[anchors]
    slot = np.asarray(part.slot_of_pose)[anchors]
    mask[rob, slot] = True
    return mask


def _gamma_entries(part: Partition, anchor_mask: np.ndarray, xi: float, d: int, rotation: bool, dtype, planar: bool):
    """Every robot's Gamma^alpha as entries (robot, row, column, value) whose duplicates sum, rows and
    columns numbered within the robot (N = n_max b of them, b = d for non-planar rotations, else 1),
    the diagonal's xi (1 on padding slots) included and the anchors' rows and columns left out
    (their identity is added by the caller): one scatter of the edge blocks, no loop over robots.
    An own edge adds its four blocks, an inter-robot edge twice its local end's diagonal block
    (Eq. (24)), padding edges nothing. Returns (robot, row, col, value, N, anchor (robot, index) pairs)."""
    e = part.edges
    A, n_max = part.pose_mask.shape
    b = d if rotation and not planar else 1
    N = n_max * b
    loc_i, loc_j = np.asarray(e.local_i), np.asarray(e.local_j)
    si = np.asarray(e.slot_i, dtype=np.int64)
    sj = np.asarray(e.slot_j, dtype=np.int64)
    w = np.asarray(e.kappa if rotation else e.tau, dtype=np.float64).reshape(-1)
    Rm = np.asarray(e.R, dtype=np.float64).reshape(-1, d, d)
    tm = np.asarray(e.t, dtype=np.float64).reshape(-1, d)
    # the edges' connection-Laplacian blocks with only kappa (rotations) or only tau (translations)
    part_of = slice(1, None) if rotation else slice(0, 1)
    Hii, Hjj, Hij = (H[:, part_of, part_of] for H in
                     edge_hessian_blocks(Rm, tm, *((w, 0.0) if rotation else (0.0, w))))
    own = (loc_i & loc_j).reshape(-1)
    # coefficient of each block instance: own edges 1; an inter-robot edge 2 at its local end
    c_ii = np.where(own, 1.0, 2.0 * (loc_i & ~loc_j).reshape(-1))
    c_jj = np.where(own, 1.0, 2.0 * (loc_j & ~loc_i).reshape(-1))
    c_ij = own.astype(np.float64)
    robot = np.repeat(np.arange(A), si.shape[1])
    index = b * np.arange(n_max)[:, None] + np.arange(b)  # (n_max, b) rows/columns of each slot
    ri, rj = index[si.reshape(-1)], index[sj.reshape(-1)]  # (A e_max, b)
    rows = np.concatenate([ri, rj, ri, rj])
    cols = np.concatenate([ri, rj, rj, ri])
    blocks = np.concatenate([c_ii[:, None, None] * Hii, c_jj[:, None, None] * Hjj,
                             c_ij[:, None, None] * Hij, c_ij[:, None, None] * np.swapaxes(Hij, 1, 2)])
    if planar:  # [[a, -b], [b, a]] -> a + i b
        blocks = (blocks[:, 0, 0] + 1j * blocks[:, 1, 0])[:, None, None]
    shape = (len(rows), rows.shape[1], cols.shape[1])  # (blocks, block rows, block columns)
    robot = np.broadcast_to(np.tile(robot, 4)[:, None, None], shape).reshape(-1)
    row = np.broadcast_to(rows[:, :, None], shape).reshape(-1)
    col = np.broadcast_to(cols[:, None, :], shape).reshape(-1)
    value = blocks.reshape(-1).astype(dtype)
    diagonal = np.arange(N)
    robot = np.concatenate([robot, np.repeat(np.arange(A), N)])
    row, col = np.concatenate([row, np.tile(diagonal, A)]), np.concatenate([col, np.tile(diagonal, A)])
    value = np.concatenate([value, np.where(np.repeat(np.asarray(part.pose_mask), b, axis=1), xi, 1.0)
                            .reshape(-1).astype(dtype)])
    anchors = np.nonzero(np.repeat(anchor_mask, b, axis=1))  # the anchors' rows and columns
    return robot, row, col, value, N, anchors


def _gamma_matrices(part: Partition, anchor_mask: np.ndarray, xi: float, d: int, rotation: bool,
                    dtype=np.float64, planar: bool = False) -> np.ndarray:
    """(A, N, N) dense Gamma_R^alpha (N = n_max d) or Gamma_t^alpha (N = n_max) of every robot
    (:func:`_gamma_entries`), the anchors' rows and columns replaced by the identity's (the anchor
    is eliminated). In ``dtype`` (the edge blocks are summed in it).

    Rotation layout: row/column ``slot*d + a`` acts on the transposed block R_slot^T. ``planar``
    (rotations, d = 2, :func:`_planar`): the complex (A, n_max, n_max) matrix of those 2 x 2 blocks.
    """
    A = part.pose_mask.shape[0]
    if planar:
        dtype = np.result_type(dtype, np.complex64)
    robot, row, col, value, N, (robot_of, fixed) = _gamma_entries(part, anchor_mask, xi, d, rotation, dtype, planar)
    # one sparse (A N) x N matrix whose duplicates sum, written out dense (C speed, no N^2 index array)
    G = sp.coo_matrix((value, (robot * N + row, col)), shape=(A * N, N)).toarray().reshape(A, N, N)
    G[robot_of, fixed, :] = 0.0
    G[robot_of, :, fixed] = 0.0
    G[robot_of, fixed, fixed] = 1.0
    return G


def _gamma_sparse(part: Partition, anchor_mask: np.ndarray, xi: float, d: int, rotation: bool,
                  planar: bool = False) -> sp.csc_matrix:
    """All robots' Gamma^alpha as one block-diagonal sparse (A N) x (A N) matrix (float64, or
    complex128 with ``planar``), robot alpha's block at rows and columns alpha N .. alpha N + N - 1
    in :func:`_gamma_matrices`' numbering, the anchors' rows and columns those of the identity."""
    A = part.pose_mask.shape[0]
    dtype = np.complex128 if planar else np.float64
    robot, row, col, value, N, (robot_of, fixed) = _gamma_entries(part, anchor_mask, xi, d, rotation, dtype, planar)
    anchored = np.zeros((A, N), bool)
    anchored[robot_of, fixed] = True
    keep = ~(anchored[robot, row] | anchored[robot, col])
    ones = robot_of * N + fixed
    index_r = np.concatenate([(robot * N + row)[keep], ones])
    index_c = np.concatenate([(robot * N + col)[keep], ones])
    value = np.concatenate([value[keep], np.ones(len(ones), dtype)])
    gamma = sp.csc_matrix((value, (index_r, index_c)), shape=(A * N, A * N))  # duplicates summed
    gamma.eliminate_zeros()  # e.g. the off-diagonal entries of kappa I blocks: no fill to carry
    return gamma


def _gamma_inverses(part: Partition, anchor_mask: np.ndarray, xi: float, d: int, rotation: bool,
                    single: bool = False, double: bool = True) -> np.ndarray | None:
    """Every robot's Gamma^{-1}, each from its Cholesky factor: (A, N, N), or for planar rotations
    (A, 2, n_max, n_max), the real and imaginary parts of the complex n_max x n_max inverse
    (:func:`_planar`). With ``single`` in float32 when every robot's float32 factorization succeeds
    (else float64; without ``double``, None where float32 was refused for its precision alone: the
    caller has another way)."""
    planar = rotation and d == 2 and _planar(part)
    for dtype in ((np.float32,) if single else ()) + (np.float64,):
        G = _gamma_matrices(part, anchor_mask, xi, d, rotation, dtype, planar)  # assembled in dtype too
        out = np.empty((G.shape[0], 2, *G.shape[1:]), dtype) if planar else None
        # float32 only where its rounding leaves the preconditioner within SINGLE_PRECISION_ERROR
        max_condition = SINGLE_PRECISION_ERROR / np.finfo(np.float32).eps if dtype == np.float32 else None
        bad = _invert_in_place(G, out, max_condition)
        if bad is None:
            return G if out is None else out
        if dtype == np.float32 and not double and bad[1] == 0:
            return None
    robot, info = bad
    raise ValueError(
        f"Gamma of robot {robot} is not positive definite (LAPACK info {info}); use xi > 0 or check the weights"
    )


def _planar(part: Partition) -> bool:
    """Whether every measured rotation is a planar rotation [[c, -s], [s, c]]: then every 2 x 2 block
    of Gamma_R^alpha (and of its inverse) is one too, a complex number c + i s acting on the rows
    of R^T as complex numbers. The complex inverse reads half the bytes of the real one per
    iteration, and its factorization takes about half the operations."""
    R = np.asarray(part.edges.R).reshape(-1, 2, 2)
    scale = max(1.0, float(np.abs(R).max(initial=0.0)))
    return bool(np.allclose(R[:, 0, 0], R[:, 1, 1], rtol=0, atol=1e-12 * scale)
                and np.allclose(R[:, 1, 0], -R[:, 0, 1], rtol=0, atol=1e-12 * scale))


def _invert_in_place(G: np.ndarray, out: np.ndarray | None = None,
                     max_condition: float | None = None) -> tuple[int, int] | None:
    """Every G[a] (symmetric or Hermitian positive definite) replaced by its inverse (LAPACK potrf,
    trtri and lauum: potri's steps, in G's precision), or for complex G written to
    ``out[a] = (real part, imaginary part)``; (robot, info) of the first failure. With
    ``max_condition``, a robot whose condition number (1-norm, LAPACK's ``pocon`` estimate from the
    Cholesky factor) exceeds it fails too (info 0).

    Between the steps the entries below eps^2 of the largest are set to zero (:func:`_flush_tiny`):
    these inverses decay along the graph (city10000's float32 inverse is 77 % exact zeros after
    underflow), and products of those tiny entries are subnormal numbers, which the CPU handles in
    microcode: potri took 110 ms per robot of city10000 (N = 1000, complex) against 45 ms for a
    random matrix, and the flushed steps 60 ms (float32 2.0 s -> 0.6 s for its 10 robots)."""
    potrf, pocon, trtri, lauum = sla.lapack.get_lapack_funcs(("potrf", "pocon", "trtri", "lauum"), (G,))
    upper = np.triu(np.ones(G.shape[1:], bool), 1)
    # the one loop over robots left in the set-up, each pass an O(N^3) LAPACK call. NumPy and SciPy
    # have no batched potri; the batched alternatives (np.linalg.inv, a batched Cholesky and
    # triangular solves) do 3x the flops (measured 3.5x slower for N = 1500).
    for a in range(G.shape[0]):
        norm = np.abs(G[a]).sum(axis=0).max() if max_condition is not None else 0.0  # 1-norm, before potrf
        c, info = potrf(G[a], lower=1, clean=1, overwrite_a=1)  # clean: no stale upper triangle
        if info == 0 and max_condition is not None and pocon(c, norm, uplo="L")[0] * max_condition < 1.0:
            return a, 0
        if info == 0:
            c, info = trtri(_flush_tiny(c), lower=1, overwrite_c=1)
        if info == 0:
            c, info = lauum(_flush_tiny(c), lower=1, overwrite_c=1)  # L^-H L^-1, lower triangle
        if info != 0:
            return a, int(info)
        np.copyto(c, c.T.conj(), where=upper)  # lauum writes the lower triangle only
        if out is None:
            G[a] = c
        else:
            out[a, 0], out[a, 1] = c.real, c.imag
    return None


def _flush_tiny(c: np.ndarray) -> np.ndarray:
    """``c`` with its entries below eps^2 times its largest set to zero, in place. Harmless to the
    result: the dropped part has a norm below N eps^2 of c's, under the rounding of the
    factorization itself for N < 1 / eps; what it removes is the subnormal products of tiny entries
    (each at least eps^4 of the largest product)."""
    magnitude = np.abs(c)
    c[magnitude < np.finfo(c.dtype).eps ** 2 * magnitude.max(initial=0.0)] = 0
    return c


class SparseFactors:
    """Every robot's Gamma^alpha factored sparse (SuperLU, :func:`scipy.sparse.linalg.splu`, of the
    block-diagonal matrix of all robots: robot alpha's factor is the factorization of its own block,
    the robots are independent), applied on the host from inside the compiled iteration
    (``jax.pure_callback``, one call per iteration for all robots). A factor is registered under an
    integer handle, which the compiled programs take as a traced argument: the same program serves
    every graph of the same shapes, and :meth:`release` drops the factor when its stage is done."""

    _live: ClassVar[dict] = {}
    _next = 0

    @classmethod
    def register(cls, gamma: sp.csc_matrix) -> int:
        """Factor ``gamma`` (real, or complex for planar rotations: :func:`_gamma_sparse`)."""
        # symmetric (Hermitian) positive definite: a symmetric fill-reducing ordering, diagonal pivots
        lu = spla.splu(gamma, permc_spec="MMD_AT_PLUS_A", diag_pivot_thresh=0.0, options=dict(SymmetricMode=True))
        cls._next += 1
        cls._live[cls._next] = (lu, np.iscomplexobj(gamma.data))
        return cls._next

    @classmethod
    def release(cls, handle) -> None:
        cls._live.pop(int(handle), None)

    @classmethod
    def solve(cls, handle, rhs):
        """Gamma^{-1} rhs for every robot; a complex factor (planar rotations) reads each slot's four
        numbers (its transposed 2 x 2 block) as two complex ones, as :func:`_apply_planar_inverse`."""
        lu, planar = cls._live[int(handle)]
        if not planar:
            return lu.solve(np.asarray(rhs, np.float64)).astype(rhs.dtype, copy=False)
        Z = np.asarray(rhs).reshape(-1, 4)
        w = lu.solve(Z[:, :2] + 1j * Z[:, 2:])
        return np.concatenate([w.real, w.imag], axis=1).astype(rhs.dtype, copy=False).reshape(rhs.shape)


def _apply_sparse(handle, G):
    """Gamma^{-1} applied to every robot's block of ``G`` (A, n_max, ...): the rows of its reshape to
    (A N, columns) are :func:`_gamma_sparse`'s numbering (rotations held transposed: row
    ``slot*d + a``, column k)."""
    flat = G.reshape(-1, G.shape[-1])
    out = jax.pure_callback(SparseFactors.solve, jax.ShapeDtypeStruct(flat.shape, flat.dtype), handle, flat,
                            vmap_method="sequential")
    return out.reshape(G.shape)


# --------------------------------------------------------------------------------------------
# per-robot gradients (vmapped over robots)
# --------------------------------------------------------------------------------------------


def _rotation_gradient_one(edges, anchor, Y, n_max: int):
    """grad_alpha F_R and the robot's cost share at the padded global iterate held transposed,
    Y (A, n_max, d, d) with Y_i = R_i^T (:class:`RotationStage`); the gradient is returned transposed.

    E^T = Rt^T R_i^T - R_j^T; the gradient w.r.t. R_i is kappa E Rt^T (transposed: Rt kappa E^T), the
    one w.r.t. R_j is -kappa E. The small products are unrolled (:func:`bmm`: XLA:CPU's batched dot of
    2 x 2 / 3 x 3 matrices is slower). Cost share in the 2F convention: own edges fully, inter-robot
    edges half, so that the shares sum to 2 F_R.
    """
    Yi = Y[edges.robot_i, edges.slot_i]
    Yj = Y[edges.robot_j, edges.slot_j]
    Et = bmm(mT(edges.R), Yi) - Yj
    wEt = edges.kappa[:, None, None] * Et
    gi = jnp.where(edges.local_i[:, None, None], bmm(edges.R, wEt), 0.0)
    gj = jnp.where(edges.local_j[:, None, None], wEt, 0.0)
    g = jax.ops.segment_sum(gi, edges.slot_i, n_max) - jax.ops.segment_sum(gj, edges.slot_j, n_max)
    g = jnp.where(anchor[:, None, None], 0.0, g)
    share = jnp.sum(jnp.where(edges.is_inter, 0.5, 1.0) * jnp.sum(wEt * Et, axis=(-1, -2)))
    return g, share


def _translation_gradient_one(edges, anchor, v, t, n_max: int):
    """Same for the translation problem; ``v`` (e_max, d) = R_i tt_e with the fixed rotations."""
    ti = t[edges.robot_i, edges.slot_i]
    tj = t[edges.robot_j, edges.slot_j]
    r = v + ti - tj
    wr = edges.tau[:, None] * r
    gi = jnp.where(edges.local_i[:, None], wr, 0.0)
    gj = jnp.where(edges.local_j[:, None], wr, 0.0)
    g = jax.ops.segment_sum(gi, edges.slot_i, n_max) - jax.ops.segment_sum(gj, edges.slot_j, n_max)
    g = jnp.where(anchor[:, None], 0.0, g)
    share = jnp.sum(jnp.where(edges.is_inter, 0.5, 1.0) * jnp.sum(wr * r, axis=-1))
    return g, share


def _rotation_gradient(edges, anchor, R):
    n_max = anchor.shape[1]
    g, share = jax.vmap(_rotation_gradient_one, in_axes=(0, 0, None, None))(edges, anchor, R, n_max)
    return g, jnp.sum(share)


def _translation_gradient(edges, anchor, v, t):
    n_max = anchor.shape[1]
    g, share = jax.vmap(_translation_gradient_one, in_axes=(0, 0, 0, None, None))(edges, anchor, v, t, n_max)
    return g, jnp.sum(share)


def _apply_inverse_rot(Ginv, G):
    """The step of every robot, G Gamma^{-1} in block form, for G held transposed (A, n_max, d, d):
    the blocks G_i^T stacked are the columns Gamma^{-1} acts on (its rows ``slot*d + a``), so no
    block is transposed here. In Ginv's precision (float32 for the CG preconditioner), returned in G's."""
    if Ginv.ndim == 4:
        return _apply_planar_inverse(Ginv, G)
    A, n_max, d, _ = G.shape
    sol = jnp.einsum("aij,ajk->aik", Ginv, G.reshape(A, n_max * d, d).astype(Ginv.dtype))
    return sol.astype(G.dtype).reshape(G.shape)


def _apply_planar_inverse(Ginv, G):
    """:func:`_apply_inverse_rot` with the complex inverse (Hr, Hi) = Ginv[:, 0], Ginv[:, 1]: row k of
    every block G_s (column k of the transposed block held), G_s[k, 0] + i G_s[k, 1], is the complex
    number z_k[s]; w_k = (Hr + i Hi) z_k. The held block (G_s^T) read row by row is (Re z, Im z)."""
    A, n_max = G.shape[:2]
    Z = G.reshape(A, n_max, 4).astype(Ginv.dtype)  # (A, n_max, 4): Re z_0, Re z_1, Im z_0, Im z_1
    PQ = jnp.einsum("apij,ajk->apik", Ginv, Z)  # Hr Z and Hi Z in one pass over the inverse
    P, Q = PQ[:, 0], PQ[:, 1]
    wr = P[..., :2] - Q[..., 2:]
    wi = P[..., 2:] + Q[..., :2]
    return jnp.concatenate([wr, wi], axis=-1).astype(G.dtype).reshape(G.shape)


def _apply_inverse_trans(Ginv, g):
    return jnp.einsum("aij,ajk->aik", Ginv, g.astype(Ginv.dtype)).astype(g.dtype)


# --------------------------------------------------------------------------------------------
# the accelerated MM iteration (shared by both stages)
# --------------------------------------------------------------------------------------------


class _Stage(eqx.Module):
    """The constant data of one stage: the robots' incident edges, the anchor slots and the inverse
    of every robot's Gamma (factored once on the host)."""

    edges: object
    anchor: jax.Array
    Ginv: jax.Array  # the dense inverses, or with ``sparse`` the handle of the robots' sparse factors
    sparse: bool = eqx.field(static=True)

    @property
    def exportable(self) -> bool:
        """Whether the stage's programs can be serialized (``jax.export``) into the persistent cache:
        not with the sparse factors' host callback."""
        return not self.sparse

    @property
    def pose_slots(self) -> int:
        """The padded pose slots (robots x poses per robot): the size the compile mode reads."""
        return int(np.size(self.anchor))

    def gradient(self, X):
        """(grad F(X) per robot, the relaxed objective 2F(X))."""
        raise NotImplementedError

    def apply_inverse(self, G):
        raise NotImplementedError

    def matvec(self, P):
        """The objective's Hessian (the anchored Laplacian) applied to a direction P that is zero on
        the anchor slots: one exchange of P's values at the ends of inter-robot edges."""
        raise NotImplementedError

    def column_dot(self, X, Y):
        """Per right-hand-side sums over every robot of X * Y, broadcastable against X: the linear
        system has d independent columns (R^T stacked for rotations, t for translations)."""
        raise NotImplementedError


class RotationStage(_Stage):
    """The relaxed rotation problem (22) as majorized by Eq. (24), its iterate held transposed:
    blocks R_i^T (A, n_max, d, d), the layout of Gamma's rows, which the preconditioner then reads as
    they are (:func:`_run_rotations` transposes on the way in and out). Held as R itself, XLA:CPU
    transposed every block before and after each preconditioner product: more than half of a CG
    iteration's time on parking-garage (3 x 3 blocks), measured with JAX's profiler."""

    def gradient(self, Y):
        return _rotation_gradient(self.edges, self.anchor, Y)

    def apply_inverse(self, G):
        return _apply_sparse(self.Ginv, G) if self.sparse else _apply_inverse_rot(self.Ginv, G)

    def matvec(self, P):
        return _rotation_gradient(self.edges, self.anchor, P)[0]  # the gradient is linear in R

    def column_dot(self, X, Y):
        return jnp.sum(X * Y, axis=(0, 1, 2), keepdims=True)  # column k of the stacked R^T


class TranslationStage(_Stage):
    """The translation problem (25) with the rotations fixed (``v`` = R_i t~_ij per edge slot)."""

    v: jax.Array

    def gradient(self, t):
        return _translation_gradient(self.edges, self.anchor, self.v, t)

    def apply_inverse(self, g):
        return _apply_sparse(self.Ginv, g) if self.sparse else _apply_inverse_trans(self.Ginv, g)

    def matvec(self, P):
        return _translation_gradient(self.edges, self.anchor, jnp.zeros_like(self.v), P)[0]

    def column_dot(self, X, Y):
        return jnp.sum(X * Y, axis=(0, 1), keepdims=True)


class _State(eqx.Module):
    X: jax.Array  # R^k or t^k, padded (A, n_max, ...)
    Xprev: jax.Array
    G: jax.Array  # grad F(X^k)
    Gprev: jax.Array
    s: jax.Array  # (A,) Nesterov sequence s^{alpha(k)}
    k: jax.Array  # iterations done


class _StageSolver(Solver):
    """What both schemes share on the driver: states with the iterate ``X`` (A, n_max, ...) and the
    iteration count ``k``, and the per-iteration record (f, gradient norm, per-robot restarts)."""

    state_type = None  # the scheme's state module (a class attribute, not a field)

    def skipped(self, st):
        nan = jnp.full((), jnp.nan, st.X.dtype)
        return self._record(nan, None, jnp.zeros(st.X.shape[:1], bool), grad_norm=nan)

    def iteration(self, st):
        return st.k

    def record_structure(self, problem):
        return IterationRecord(f=0.0, grad_norm=0.0, restarted=0.0, settled=0.0)

    def start_structure(self, problem):
        leaves = [0.0] * len(dataclasses.fields(self.state_type))
        return self.state_type(*leaves), self.record_structure(problem)

    @staticmethod
    def _record(f, G, restarted, grad_norm=None):
        grad_norm = jnp.sqrt(jnp.sum(G**2)) if grad_norm is None else grad_norm
        return IterationRecord(f=f, grad_norm=grad_norm, restarted=restarted, settled=jnp.ones((), bool))


class AMMChordal(_StageSolver):
    """Algorithm 3 (AMM-Chordal) as a solver of the one driver: each robot's exact minimiser of the
    quadratic majorizer (Eq. (24)) from the Nesterov point, with the per-robot gradient restart
    (``restart``, module docstring). Its problems are the stages (:class:`RotationStage`,
    :class:`TranslationStage`); the driver's chunks, budget and relative-change rule
    (``Termination(budget, 10, rel_change_tol=tol)``) run it as they run MM and AMM."""

    restart: bool = eqx.field(static=True, default=DEFAULT_RESTART)
    state_type = _State

    @property
    def name(self) -> str:
        return "amm-chordal"

    def init(self, problem: _Stage, X0):
        G0, f0 = problem.gradient(X0)
        A = X0.shape[0]
        state = _State(X0, X0, G0, G0, jnp.ones((A,), X0.dtype), jnp.asarray(0, jnp.int32))
        return state, self._record(f0, G0, jnp.zeros((A,), bool))

    def step(self, problem: _Stage, st: _State, comm=None):
        axes = tuple(range(1, st.X.ndim))
        bshape = (st.X.shape[0],) + (1,) * (st.X.ndim - 1)
        # Algorithm 3, lines 11-14 (every robot at once)
        s1 = 0.5 * (jnp.sqrt(4.0 * st.s**2 + 1.0) + 1.0)
        gam = ((st.s - 1.0) / s1).reshape(bshape)
        Y = st.X + gam * (st.X - st.Xprev)
        GY = st.G + gam * (st.G - st.Gprev)
        Z = Y - problem.apply_inverse(GY)
        uphill = jnp.zeros(st.s.shape, bool)
        if self.restart:
            # per-robot gradient restart: momentum is dropped where the step goes uphill
            uphill = jnp.sum(GY * (Z - st.X), axis=axes) > 0
            s1 = jnp.where(uphill, 1.0, s1)
        GZ, fZ = problem.gradient(Z)  # line 17 (one exchange of boundary poses)
        return _State(Z, st.X, GZ, st.G, s1, st.k + 1), self._record(fZ, GZ, uphill)


class _CGState(eqx.Module):
    X: jax.Array  # the iterate, padded (A, n_max, ...)
    r: jax.Array  # residual = -grad F(X) (zero on anchor and padding slots)
    z: jax.Array  # preconditioned residual Gamma^{-1} r
    p: jax.Array  # search direction
    rz: jax.Array  # per-column <r, Gamma^{-1} r>
    f: jax.Array  # the relaxed objective 2F(X), updated exactly along each step
    k: jax.Array  # iterations done


class CGChordal(_StageSolver):
    """Conjugate gradients on each stage's quadratic, preconditioned by every robot's Gamma^alpha
    (the same factored matrices as :class:`AMMChordal`'s majorizer: block Jacobi over the robots).

    One iteration: the Hessian applied to the search direction (one exchange of each robot's
    poses at the ends of its inter-robot edges, as an AMM-Chordal iteration), each robot's
    preconditioner solve, and two sums over all robots of d numbers each (the step length and the
    conjugacy coefficient of every column: an all-reduce, which AMM-Chordal does not need). The
    objective is updated along the step exactly (a quadratic), so it is non-increasing."""

    state_type = _CGState

    @property
    def name(self) -> str:
        return "cg-chordal"

    def init(self, problem: _Stage, X0):
        G0, f0 = problem.gradient(X0)
        r = -G0
        z = problem.apply_inverse(r)
        state = _CGState(X0, r, z, z, problem.column_dot(r, z), f0, jnp.asarray(0, jnp.int32))
        return state, self._record(f0, r, jnp.zeros(r.shape[:1], bool))

    def step(self, problem: _Stage, st: _CGState, comm=None):
        Ap = problem.matvec(st.p)
        pAp = problem.column_dot(st.p, Ap)
        rp = problem.column_dot(st.r, st.p)
        alpha = jnp.where(pAp > 0, rp / jnp.where(pAp > 0, pAp, 1.0), 0.0)
        X = st.X + alpha * st.p
        # 2F(X + alpha p) = 2F(X) - 2 alpha <r, p> + alpha^2 <p, H p>, per column
        f = st.f + jnp.sum(alpha * (alpha * pAp - 2.0 * rp))
        r = st.r - alpha * Ap
        z = problem.apply_inverse(r)
        # Polak-Ribiere's beta (flexible CG): equal to Fletcher-Reeves' with an exact symmetric
        # preconditioner, and robust to the float32 rounding of Gamma^{-1}
        beta = problem.column_dot(r, z - st.z)
        beta = jnp.where(st.rz > 0, beta / jnp.where(st.rz > 0, st.rz, 1.0), 0.0)
        rz = problem.column_dot(r, z)
        return _CGState(X, r, z, z + beta * st.p, rz, f, st.k + 1), self._record(f, r, jnp.zeros(r.shape[:1], bool))


SCHEMES = ("cg", "amm")


def _stage_solver(scheme: str, restart: bool | None) -> Solver:
    if scheme not in SCHEMES:
        raise ValueError(f"scheme must be one of {', '.join(map(repr, SCHEMES))}, got {scheme!r}")
    if scheme == "cg":
        if restart is not None:
            raise ValueError("restart applies to scheme='amm' (Algorithm 3's momentum) only, not to 'cg'")
        return CGChordal()
    return AMMChordal(restart=DEFAULT_RESTART if restart is None else bool(restart))


def _single(solver: Solver) -> bool:
    """Whether Gamma^{-1} may be float32: as CG's preconditioner yes; as AMM-Chordal's majorizer no
    (its exact minimiser is what keeps the objective non-increasing)."""
    return isinstance(solver, CGChordal)


def _drive_stage(part: Partition, problem: _Stage, X0, budget: int, tol, solver: Solver, conditioning=None):
    """One stage of the distributed chordal start on the driver: (final iterate, f history,
    iterations, whether a tolerance stopped it). ``conditioning(X)``: the smallest singular value of
    the iterate's blocks where the stage's output is projected (the rotation stage); a stage stopped
    by ``tol`` then goes on where its residual is large against it (:func:`_projection_settled`)."""
    placement = Placement(part)
    # the start's program from the persistent cache when it is on (a warm process does not trace it)
    exported = (start_run.__wrapped__, (), solver.start_structure(problem)) if problem.exportable else None
    start_fn = compile_once(start_run, solver, problem, X0, exported=exported, once=True)
    state, start = start_fn(solver, problem, X0)
    termination = Termination(budget, _CHUNK, rel_change_tol=tol, stop_when_stalled=False)
    chunk = placement.compile_chunk(solver, problem)
    out = drive(chunk, state, placement.start_record(jax.device_get(start)), termination, fetch=placement.fetch)
    if conditioning is not None and out.result is RESULTS.rel_change_tol and out.history.iterations < budget:
        target = _projection_settled(out.history.grad_norm, conditioning(out.state.X), tol)
        if target is not None:  # the same iteration goes on (one compiled chunk, its state kept)
            out = drive(chunk, out.state, None, Termination(budget, _CHUNK, grad_tol=target, stop_when_stalled=False),
                        fetch=placement.fetch, history=out.history)
    converged = out.result in (RESULTS.rel_change_tol, RESULTS.grad_tol)
    return out.state.X, out.history.f, out.history.iterations, converged


def _projection_settled(grad_norm: np.ndarray, sigma: float, tol: float) -> float | None:
    """The residual norm a stage stopped by its relative-change ``tol`` must reach before its output
    is projected, or None where it already has. The rotation stage's relaxed blocks are projected to
    SO(d), which multiplies their error by 1 / ``sigma`` (the smallest singular value of a block);
    where the relaxation collapses (long noisy chains: sigma 2e-8 on the 15 000-pose chain graph of
    benchmarks/vs_authors.md, against 0.013-0.99 on the benchmark files) the objective agrees with
    its optimum to 11 digits while the projected rotations are still wrong by radians, and the
    translations follow them along the chains (f at the start +500 % against the centralized
    start's). So the relative residual (CG's error bound up to the conditioning) must be within
    sqrt(tol) sigma: the relative-change rule holds f to tol, i.e. the iterate to about sqrt(tol),
    and that bound is asked of the projected blocks. None too where there is nothing to ask: a
    stage that starts at its solution (residual 0: an exact graph) or blocks of no rank."""
    bound = np.sqrt(tol) * sigma
    if not (grad_norm[0] > 0 and bound > 0):
        return None
    return None if grad_norm[-1] / grad_norm[0] <= bound else float(bound * grad_norm[0])


def _smallest_singular_value(st: _Setup):
    """``conditioning`` of the rotation stage: the smallest singular value of the relaxed blocks of
    the free poses (not anchors, not padding), on the host."""
    free = np.asarray(st.part.pose_mask) & ~np.asarray(st.anchor)

    def sigma(X):
        blocks = np.asarray(X)[free]
        return float(np.linalg.svd(blocks, compute_uv=False)[:, -1].min(initial=1.0))

    return sigma


# --------------------------------------------------------------------------------------------
# public API
# --------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class DistributedChordalInfo:
    """What :func:`distributed_chordal_initialization` did.

    ``*_history[k]`` is the relaxed objective in the 2F convention (2 F_R of Eq. (23) for
    rotations, 2 F_t of Eq. (26) for translations) after k iterations, k = 0..iterations.
    """

    rotation_iterations: int
    translation_iterations: int
    rotation_converged: bool
    translation_converged: bool
    rotation_history: np.ndarray
    translation_history: np.ndarray
    num_robots: int
    xi: float
    tol: float | None
    scheme: str
    restart: bool  # AMM-Chordal's per-robot momentum restart (False for "cg")
    factorizations: tuple[str, str] = ("dense", "dense")  # how Gamma^alpha was applied: rotations, translations


def _as_partition(graph: PoseGraph, robots) -> Partition:
    if isinstance(robots, Partition):
        if robots.num_poses != graph.num_poses:
            raise ValueError(f"partition is for {robots.num_poses} poses, graph has {graph.num_poses}")
        return robots
    return make_partition(graph, robots)


def _check_iters(name, value) -> int:
    check_count(None, name, value, 0, scalar=True)
    return int(value)


def _check_tol(tol) -> float | None:
    check_real(None, "tol", tol, 0.0, optional=True, scalar=True)
    return None if tol is None else float(tol)


class _Setup(eqx.Module):
    """A partition plus the padded anchor mask (host-side set-up shared by both stages). The glue
    between the stages (starts, projection, unpadding) runs in NumPy on the host: as JAX operations
    each would be a small program traced and loaded in every process (44 of them, about 0.4 s of a
    0.5 s MIT start, measured), where the stages' own compiled programs are four."""

    part: Partition
    anchor: np.ndarray  # (A, n_max) bool: the slots of the anchor poses
    anchor_R: np.ndarray  # (A, n_max, d, d): their rotations (I elsewhere)
    anchor_t: np.ndarray  # (A, n_max, d): their translations (0 elsewhere)
    dim: int = eqx.field(static=True)
    dtype: object = eqx.field(static=True)

    def gamma_inverse(self, xi: float, rotation: bool, single: bool = False, sparse: bool = False,
                      double: bool = True):
        """Every robot's Gamma^{-1} in the graph's precision, or with ``single`` in float32 where its
        factorization succeeds (a preconditioner needs no more: half the bytes each iteration reads;
        where it does not, None without ``double``). ``sparse``: the robots' sparse factors instead
        (:class:`SparseFactors`), returned as their handle (an int), to be released when the stage
        is done."""
        if sparse:
            planar = rotation and self.dim == 2 and _planar(self.part)
            return SparseFactors.register(_gamma_sparse(self.part, np.asarray(self.anchor), float(xi), self.dim,
                                                        rotation, planar))
        _check_memory(self.part, self.dim if rotation else 1, np.dtype(self.dtype).itemsize)
        G = _gamma_inverses(self.part, np.asarray(self.anchor), float(xi), self.dim, rotation, single, double)
        if G is None:
            return None
        return jnp.asarray(G, np.float32 if G.dtype == np.float32 else self.dtype)


def _check_memory(part: Partition, b: int, itemsize: int) -> None:
    """Refuse, in one line, dense inverses that cannot fit in memory: A N^2 float64 on the host
    while they are built (plus an A N^2 boolean mask), then a copy in the solver's precision."""
    A, n_max = part.pose_mask.shape
    N = n_max * b
    need = A * N * N * (8 + 1 + itemsize)
    available = available_memory_bytes()
    if need > available:
        raise ValueError(
            f"distributed-chordal initialization holds a dense {N} x {N} inverse per robot: {A} robots need "
            f"about {need / 1e9:.1f} GB, more than the {available / 1e9:.1f} GB of memory available; "
            "use factorization='sparse' (or 'auto'), more robots (the memory falls as 1 / robots) or init='chordal'")


def _setup(graph: PoseGraph, robots, fixed: FixedPoses | None = None) -> _Setup:
    part = _as_partition(graph, robots)
    anchors = anchor_set(graph, fixed)
    n, d, dt = graph.num_poses, graph.dim, jnp.asarray(graph.R).dtype
    R = np.broadcast_to(np.eye(d), (n, d, d)).copy()
    t = np.zeros((n, d))
    R[anchors.index], t[anchors.index] = anchors.R, anchors.t
    values = part.scatter(Poses(R.astype(dt), t.astype(dt)), host=True)
    return _Setup(part, _padded_anchor_mask(part, anchors.index), values.R, values.t, d, dt)


def _initial_rotations(st: _Setup, initial, n: int) -> np.ndarray:
    d, dt = st.dim, st.dtype
    if initial is None:
        R0g = np.broadcast_to(np.eye(d, dtype=dt), (n, d, d))
    else:
        R0g = np.asarray(initial, dt)
        if R0g.shape != (n, d, d):
            raise ValueError(f"initial rotations must have shape ({n}, {d}, {d}), got {R0g.shape}")
    R0 = st.part.scatter(Poses(R0g, np.zeros((n, d), dt)), host=True).R
    return np.where(st.anchor[..., None, None], st.anchor_R, R0)


def _initial_translations(st: _Setup, initial, n: int) -> np.ndarray:
    d, dt = st.dim, st.dtype
    if initial is None:
        return st.anchor_t
    t0 = np.asarray(initial, dt)
    if t0.shape != (n, d):
        raise ValueError(f"initial translations must have shape ({n}, {d}), got {t0.shape}")
    t0 = st.part.scatter(Poses(np.zeros((n, d, d), dt), t0), host=True).t
    return np.where(st.anchor[..., None], st.anchor_t, t0)


def _run_rotations(st: _Setup, Ginv, R0, budget: int, tol, solver: Solver):
    """The rotation stage on the driver; ``budget`` and ``tol`` are traced (the compiled chunk of 10
    iterations serves every budget and tolerance). The stage holds the blocks transposed
    (:class:`RotationStage`): ``R0`` (host) and the result are transposed here, on the host."""
    stage = RotationStage(st.part.edges, jnp.asarray(st.anchor), *_inverse_field(Ginv))
    Y, history, k, converged = _drive_stage(st.part, stage, jnp.asarray(np.swapaxes(R0, -1, -2)), budget,
                                            _check_tol(tol), solver, conditioning=_smallest_singular_value(st))
    return np.swapaxes(np.asarray(Y), -1, -2), history, k, converged


def _run_translations(st: _Setup, Ginv, Rpad, t0, budget: int, tol, solver: Solver):
    """As :func:`_run_rotations`, for the translation stage with the rotations ``Rpad`` (host) fixed."""
    edges = st.part.edges
    # v_e = R_i tt_e with the fixed rotations, per robot edge slot (constant over iterations)
    Rpad = np.asarray(Rpad)
    v = np.einsum("aexy,aey->aex", Rpad[np.asarray(edges.robot_i), np.asarray(edges.slot_i)], np.asarray(edges.t))
    stage = TranslationStage(edges, jnp.asarray(st.anchor), *_inverse_field(Ginv), v=jnp.asarray(v))
    return _drive_stage(st.part, stage, jnp.asarray(t0), budget, _check_tol(tol), solver)


def _inverse_field(Ginv) -> tuple:
    """A stage's (``Ginv``, ``sparse``) fields from :meth:`_Setup.gamma_inverse`'s result."""
    if isinstance(Ginv, int):  # the handle of sparse factors
        return jnp.asarray(Ginv, jnp.int32), True
    return Ginv, False


def _check_factorization(factorization) -> str:
    if factorization not in FACTORIZATIONS:
        raise ValueError(f"factorization must be one of {', '.join(map(repr, FACTORIZATIONS))}, got {factorization!r}")
    return factorization


def _dense_inverse_bytes(st: _Setup, rotation: bool, single: bool) -> int:
    """The bytes of all robots' dense Gamma^{-1} of a stage: what each of its iterations reads."""
    A, n_max = st.part.pose_mask.shape
    planar = rotation and st.dim == 2 and _planar(st.part)
    N = n_max * (st.dim if rotation and not planar else 1)
    itemsize = 4 if single else np.dtype(st.dtype).itemsize
    return A * N * N * itemsize * (2 if planar else 1)


def _use_sparse(st: _Setup, rotation: bool, single: bool, factorization: str) -> bool:
    """Whether a stage applies sparse factors (module docstring, "Factorization"). ``"auto"``: on
    the CPU, where the dense inverses (float32 with ``single``) exceed the largest CPU cache (each
    iteration would then stream them from memory); on other backends only where they would not fit
    in memory (the sparse solve runs on the host, a transfer each iteration). Where float32 inverses
    are refused (:func:`_gamma_inverses`), the float64 ones are sized again."""
    if factorization != "auto":
        return factorization == "sparse"
    need = _dense_inverse_bytes(st, rotation, single)
    if need > available_memory_bytes():
        return True
    return jax.default_backend() == "cpu" and need > last_level_cache_bytes()


@contextlib.contextmanager
def _preconditioner(st: _Setup, xi: float, rotation: bool, solver: Solver, factorization: str):
    """A stage's Gamma^{-1}: dense inverses, or the handle of sparse factors released afterwards."""
    single = _single(solver)
    sparse = _use_sparse(st, rotation, single, factorization)
    # where float32 is refused and the float64 inverses are over the size, no float64 ones are made
    double = sparse or not single or not _use_sparse(st, rotation, False, factorization)
    Ginv = st.gamma_inverse(xi, rotation, single, sparse, double)
    if Ginv is None:
        Ginv = st.gamma_inverse(xi, rotation, single, True)
    try:
        yield Ginv
    finally:
        if isinstance(Ginv, int):
            SparseFactors.release(Ginv)


def _unpad(st: _Setup, X):
    """Padded (A, n_max, ...) -> global (n, ...), on the host, returned on the device (a transfer)."""
    return jnp.asarray(np.asarray(X)[np.asarray(st.part.robot_of_pose), np.asarray(st.part.slot_of_pose)])


def distributed_relaxed_rotations(
    graph: PoseGraph,
    robots=10,
    *,
    iterations: int = DEFAULT_ROTATION_ITERATIONS,
    xi: float = DEFAULT_XI,
    tol: float | None = DEFAULT_TOL,
    scheme: str = DEFAULT_SCHEME,
    restart: bool | None = None,
    initial=None,
    factorization: str = DEFAULT_FACTORIZATION,
):
    """The relaxed rotation problem (22), distributed: ``scheme`` ``"cg"`` (default, preconditioned
    conjugate gradients, :class:`CGChordal`) or ``"amm"`` (AMM-Chordal, Algorithm 3, with the
    per-robot ``restart``, default True).

    ``robots``: a robot count (contiguous blocks), an (n,) robot-of-pose array or a Partition.
    ``initial``: R^(0) (n, d, d); default every block I (anchor poses are always I).
    ``iterations`` and ``tol`` are traced: another tolerance or budget reuses the compiled chunk
    (module docstring, "Stopping").
    ``factorization``: how every robot's Gamma^alpha is applied, ``"auto"``, ``"dense"`` or
    ``"sparse"`` (module docstring, "Factorization").
    Returns (R (n, d, d) not projected, history (k+1,) of 2 F_R, iterations used k, converged).
    """
    iterations = _check_iters("iterations", iterations)
    tol = _check_tol(tol)
    factorization = _check_factorization(factorization)
    solver = _stage_solver(scheme, restart)
    st = _setup(graph, robots)
    with _preconditioner(st, xi, True, solver, factorization) as Ginv:
        X, history, k, converged = _run_rotations(st, Ginv, _initial_rotations(st, initial, graph.num_poses),
                                                  iterations, tol, solver)
    return _unpad(st, X), history, k, converged


def distributed_translations(
    graph: PoseGraph,
    R,
    robots=10,
    *,
    iterations: int = DEFAULT_TRANSLATION_ITERATIONS,
    xi: float = DEFAULT_XI,
    tol: float | None = DEFAULT_TOL,
    scheme: str = DEFAULT_SCHEME,
    restart: bool | None = None,
    initial=None,
    factorization: str = DEFAULT_FACTORIZATION,
):
    """The translation problem (25) with rotations ``R`` (n, d, d) fixed, anchor translations 0,
    from t^(0) = ``initial`` (default 0), by ``scheme`` (as :func:`distributed_relaxed_rotations`).

    Returns (t (n, d), history (k+1,) of 2 F_t, iterations used k, converged).
    """
    iterations = _check_iters("iterations", iterations)
    tol = _check_tol(tol)
    factorization = _check_factorization(factorization)
    solver = _stage_solver(scheme, restart)
    st = _setup(graph, robots)
    n, d = graph.num_poses, graph.dim
    R = np.asarray(R, st.dtype)
    if R.shape != (n, d, d):
        raise ValueError(f"rotations must have shape ({n}, {d}, {d}), got {R.shape}")
    Rpad = st.part.scatter(Poses(R, np.zeros((n, d), st.dtype)), host=True).R
    with _preconditioner(st, xi, False, solver, factorization) as Ginv:
        X, history, k, converged = _run_translations(st, Ginv, Rpad, _initial_translations(st, initial, n),
                                                     iterations, tol, solver)
    return _unpad(st, X), history, k, converged


def distributed_chordal_initialization(
    graph: PoseGraph,
    robots=10,
    *,
    rotation_iterations: int = DEFAULT_ROTATION_ITERATIONS,
    translation_iterations: int = DEFAULT_TRANSLATION_ITERATIONS,
    xi: float = DEFAULT_XI,
    tol: float | None = DEFAULT_TOL,
    scheme: str = DEFAULT_SCHEME,
    restart: bool | None = None,
    initial_rotations=None,
    initial_translations=None,
    fixed: FixedPoses | None = None,
    factorization: str = DEFAULT_FACTORIZATION,
) -> tuple[Poses, DistributedChordalInfo]:
    """Distributed chordal initialization: the relaxed rotations (22), projection of every block to
    SO(d) (each robot its own poses, SVD with det fixed), then the translations (25) given those
    rotations, each stage by ``scheme``: ``"cg"`` (default; preconditioned conjugate gradients,
    :class:`CGChordal`) or ``"amm"`` (AMM-Chordal, the paper's Algorithm 3).

    ``robots``: number of robots (contiguous blocks of poses in index order, docs/conventions.md §4), an (n,)
    robot-of-pose array, or a :class:`Partition`. ``rotation_iterations`` /
    ``translation_iterations``: iteration budgets of the two stages. ``tol``: relative stopping
    tolerance of both stages (module docstring), None to spend the whole budgets. ``restart``
    (``"amm"`` only; default True): per-robot momentum restart (False = Algorithm 3 verbatim).
    ``xi``: proximal weight of Eq. (24).
    ``initial_rotations`` (n, d, d) / ``initial_translations`` (n, d): starting iterates
    (default: all rotations I, all translations 0). ``fixed``: poses held at their values in both
    stages (the anchors; default the first pose of every component, at identity).
    ``factorization``: how every robot's Gamma^alpha is applied in each stage: ``"auto"`` (default),
    ``"dense"`` (explicit inverses) or ``"sparse"`` (sparse factors; module docstring, "Factorization").

    Returns the poses (graph dtype) and a :class:`DistributedChordalInfo`.
    """
    rotation_iterations = _check_iters("rotation_iterations", rotation_iterations)
    translation_iterations = _check_iters("translation_iterations", translation_iterations)
    tol = _check_tol(tol)  # before any set-up work
    factorization = _check_factorization(factorization)
    solver = _stage_solver(scheme, restart)
    n = graph.num_poses
    st = _setup(graph, robots, fixed)
    R0 = _initial_rotations(st, initial_rotations, n)
    t0 = _initial_translations(st, initial_translations, n)
    with _preconditioner(st, xi, True, solver, factorization) as Ginv:
        RX, hR, kR, convR = _run_rotations(st, Ginv, R0, rotation_iterations, tol, solver)
        sparse_rotations = isinstance(Ginv, int)
    # each robot projects its own blocks; padding slots hold I, anchors keep their values
    Rpad = np.where(st.anchor[..., None, None], st.anchor_R, project_to_so(np.asarray(RX)))
    with _preconditioner(st, xi, False, solver, factorization) as Ginv:
        tX, ht, kt, convt = _run_translations(st, Ginv, Rpad, t0, translation_iterations, tol, solver)
        sparse_translations = isinstance(Ginv, int)
    info = DistributedChordalInfo(
        rotation_iterations=kR,
        translation_iterations=kt,
        rotation_converged=convR,
        translation_converged=convt,
        rotation_history=hR,
        translation_history=ht,
        num_robots=st.part.num_robots,
        xi=float(xi),
        tol=tol,
        scheme=scheme,
        restart=isinstance(solver, AMMChordal) and solver.restart,
        factorizations=("sparse" if sparse_rotations else "dense", "sparse" if sparse_translations else "dense"),
    )
    return st.part.gather(Poses(Rpad, np.asarray(tX))), info
