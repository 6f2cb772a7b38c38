"""Robust losses: M-estimators and graduated non-convexity (GNC) inside MM / AMM.

The robust objective (docs/conventions.md §10). Per edge the squared residual is

    s_ij = r^2_ij = kappa ||R_i Rt_ij - R_j||^2 + tau ||R_i tt_ij + t_i - t_j||^2

(one term of f = 2F), and F_rho(X) = 1/2 sum_ij rho_c(s_ij) with a kernel rho_c of s and a scale
c (residual units: the kernel starts to discount an edge around r = c, i.e. s = c^2). Every
kernel is normalised to rho(s) ~ s for small s, so an edge well inside the scale costs what it
costs in least squares, and reported objectives stay f = 2 F_rho = sum rho(s):

    l2             s                                   rho' = 1
    huber          s (s <= c^2), 2 c sqrt(s) - c^2     rho' = min(1, c / sqrt(s))
    cauchy         c^2 log(1 + s / c^2)                rho' = 1 / (1 + s / c^2)
    geman-mcclure  c^2 s / (c^2 + s)                   rho' = c^4 / (c^2 + s)^2
    welsch         c^2 (1 - exp(-s / c^2))             rho' = exp(-s / c^2)
    tls            min(s, c^2)                         rho' = 1 (s <= c^2), 0 beyond

Each is concave and non-decreasing in s, so rho(s) <= rho(s_k) + rho'(s_k) (s - s_k): the
least-squares majorizer of the paper with every edge's kappa and tau multiplied by the weight
w_ij = rho'(s_ij(X^k)) majorizes F_rho and touches it at X^k (Sections IV-V with weighted edges;
the authors' T-RO version does the same). MM therefore keeps F_rho non-increasing and AMM with the
paper's restart test keeps its guarantee. Gamma^alpha depends on the weights: it is rebuilt in
the compiled step (:func:`~mmpgo_jax._mm.majorization.assemble_gamma`, with the preconditioner:
:func:`~mmpgo_jax._mm.preconditioner.newton_from_gamma`) whenever the weights change.

GNC (Yang, Antonante, Tzoumas & Carlone, "Graduated non-convexity for robust spatial perception",
RA-L 2020): ``tls`` and ``geman-mcclure`` run, when a :class:`GNCConfig` is given, through a
sequence of surrogate kernels rho_mu, from a convex one (least squares in practice) to the kernel
itself. Each *stage* runs the distributed solver with fixed weights until the weighted objective
stalls (relative change per iteration below ``GNCConfig.stage_tolerance``) or for
``GNCConfig.stage_iterations``; then every robot sets the weights of its own edges in closed form,
w = rho_mu'(s), and mu moves by ``GNCConfig.factor``. The stages are part of the compiled scan
(the step decides when a stage ends); once the weights are binary (TLS) or mu has reached 1 (GM),
GNC ends and the weights stay. Without a GNCConfig every kernel is a plain M-estimator from its
start, by default the GNC-chordal start (:mod:`mmpgo_jax._init.robust_start`), which runs GNC-TLS
with stages solved from scratch and is the more reliable of the two (docs/conventions.md §10).

The scale c: with SE-Sync's noise model (docs/conventions.md §10), s of a correct edge is close to
chi^2 with d(d+1)/2 degrees of freedom (d translation, d(d-1)/2 rotation), so the default c is
sqrt(chi^2_{d(d+1)/2}(q)) at the quantile q = ``DEFAULT_QUANTILE`` (:func:`chi2_scale`). A 2D g2o
file whose angle noise has the variance 1 / I33 its information states gives s ~ chi^2_2 + 2 chi^2_1
instead (SE-Sync's kappa = I33 counts the angle twice): ``chi2_scale(2, noise="information")``.
"""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from .._core.pose_graph import host_edge_costs
from .._core.precision import array_module
from .._core.validate import check_count, check_real, concrete_value

LOSSES = ("l2", "huber", "cauchy", "geman-mcclure", "welsch", "tls")
GNC_LOSSES = ("geman-mcclure", "tls")  # kernels with a GNC schedule (tls only runs through it)
DEFAULT_QUANTILE = 0.99
_CODE = {name: k for k, name in enumerate(LOSSES)}
L2, HUBER, CAUCHY, GM, WELSCH, TLS = range(len(LOSSES))


NOISE_MODELS = ("se-sync", "information")


def _check_noise(where: str, noise) -> None:
    if noise not in NOISE_MODELS:
        raise ValueError(f"{where}.noise must be one of {', '.join(map(repr, NOISE_MODELS))}, got {noise!r}")


def correct_edge_sf(x, dim: int, noise: str = "se-sync"):
    """P(s > x) for a correct edge (small noise, isotropic blocks), s in SE-Sync's weights.
    ``noise="se-sync"``: SE-Sync's model with the edge's own kappa, tau (Langevin rotation noise of
    concentration kappa), s ~ chi^2 with d(d+1)/2 degrees of freedom. ``"information"``: the errors
    have the covariance the g2o information matrix states; the same in 3D (SE-Sync's kappa = 3 / (2
    tr(Sigma_R)) is the Langevin concentration of that variance), but in 2D SE-Sync's kappa = I33 is
    twice it (kappa ||Rot(a) - I||^2 ~ 2 a^2 / var(a)), so s = A + 2B with A ~ chi^2_2, B ~ chi^2_1,
    whose survival function is erfc(sqrt(x) / 2) + exp(-x / 2) erfi(sqrt(x) / 2) (A's exp(-a / 2)
    tail integrated over B)."""
    from scipy import special, stats

    _check_noise("correct_edge_sf", noise)
    x = np.asarray(x, dtype=np.float64)
    if dim != 2 or noise == "se-sync":
        return stats.chi2.sf(x, dim * (dim + 1) // 2)
    z = np.sqrt(np.maximum(x, 0.0)) / 2.0  # exp(-x/2) erfi(z) = 2/sqrt(pi) exp(-x/4) dawsn(z): no overflow
    return special.erfc(z) + 2.0 / np.sqrt(np.pi) * np.exp(-x / 4.0) * special.dawsn(z)


def chi2_scale(dim: int, quantile: float = DEFAULT_QUANTILE, noise: str = "se-sync") -> float:
    """c: the residual r = sqrt(s) a correct edge exceeds with probability 1 - quantile
    (:func:`correct_edge_sf`). ``noise="se-sync"`` (default): sqrt(chi^2_p(quantile)), p = d(d+1)/2,
    under SE-Sync's noise model (small noise): 3.37 in 2D, 4.10 in 3D at 0.99. A 2D file whose angle
    noise is what its information states exceeds 3.37 with probability 0.042; ``noise="information"``
    gives that model's quantile (4.04 in 2D at 0.99; 3D unchanged). Measured trade-off on files and
    random graphs: benchmarks/robust_random_graphs.md."""
    check_real("chi2_scale", "quantile", quantile, 0.0, 1.0, low_open=True)
    if quantile >= 1.0:
        raise ValueError(f"chi2_scale.quantile must be < 1, got {quantile!r}")
    if dim not in (2, 3):
        raise ValueError(f"chi2_scale.dim must be 2 or 3, got {dim!r}")
    _check_noise("chi2_scale", noise)
    from scipy import optimize, special  # here: only the default scales need them

    x_p = 2.0 * special.gammaincinv(0.25 * dim * (dim + 1), quantile)  # chi^2 with d(d+1)/2 degrees
    if dim == 3 or noise == "se-sync":
        return float(np.sqrt(x_p))
    # A + 2B lies between A + B ~ chi^2_3 and 2 (A + B): the quantile is bracketed by x_p and 2 x_p
    x = optimize.brentq(lambda v: float(correct_edge_sf(v, 2, noise)) - (1.0 - quantile), x_p, 2.0 * x_p,
                        xtol=1e-14 * x_p, rtol=4 * np.finfo(float).eps)
    return float(np.sqrt(x))


def loss_code(name) -> int:
    """The integer code of a kernel name (codes are traced: one compilation serves every kernel)."""
    if isinstance(name, (int, np.integer)) and not isinstance(name, bool) and 0 <= int(name) < len(LOSSES):
        return int(name)
    if not isinstance(name, str) or name not in _CODE:
        raise ValueError(f"unknown loss {name!r}: use {', '.join(repr(n) for n in LOSSES)}")
    return _CODE[name]


# ------------------------------------------------------------------------------------------------
# kernels as functions of s (traced kernel code: every kernel is evaluated and one selected, a few
# flops per edge; an M-estimator and GNC then share one compiled program)
# ------------------------------------------------------------------------------------------------


def rho(kernel, s, c2):
    """rho_c(s) for the kernel code ``kernel`` and c^2 = ``c2`` (elementwise); NumPy in, NumPy out
    (:func:`~mmpgo_jax._core.precision.array_module`: on the host, op-by-op JAX would compile each
    operation)."""
    xp = array_module(s)
    q = s / c2
    branches = [
        s,
        xp.where(s <= c2, s, 2.0 * xp.sqrt(c2 * s) - c2),
        c2 * xp.log1p(q),
        c2 * q / (1.0 + q),
        -c2 * xp.expm1(-q),
        xp.minimum(s, c2),
    ]
    return xp.select([kernel == k for k in range(len(LOSSES))], branches, s)


def weight(kernel, s, c2):
    """rho_c'(s): the edge weight of the majorizer at residual s (TLS: 1 up to c^2, 0 beyond)."""
    q = s / c2
    one = jnp.ones_like(s)
    branches = [
        one,
        jnp.sqrt(c2 / jnp.maximum(s, c2)),
        1.0 / (1.0 + q),
        1.0 / (1.0 + q) ** 2,
        jnp.exp(-q),
        jnp.where(s <= c2, one, 0.0),
    ]
    return jnp.select([kernel == k for k in range(len(LOSSES))], branches, one)


def loss_rho(loss, s, c):
    """rho_c(s) of the kernel named ``loss`` (a name of :data:`LOSSES` or its code), residual
    s = r^2 and scale ``c`` (residual units): the public, checked form of :func:`rho`."""
    return rho(loss_code(loss), jnp.asarray(s), jnp.asarray(c) ** 2)


def loss_weight(loss, s, c):
    """rho_c'(s), the majorizer's edge weight, of the kernel named ``loss`` (see :func:`loss_rho`)."""
    return weight(loss_code(loss), jnp.asarray(s), jnp.asarray(c) ** 2)


def _tls_band(xp, mu, c2):
    """(lo, hi): rho_mu of TLS is s below lo, c^2 above hi (lo = hi = c^2 for mu = inf)."""
    ratio = xp.where(xp.isinf(mu), 1.0, mu / (mu + 1.0))
    return ratio * c2, c2 / ratio


# inf / inf and inf - inf arise in the branches xp.where discards (mu, c^2 or s = inf): no NumPy warning
_DISCARDED = dict(invalid="ignore", divide="ignore", over="ignore")


def gnc_rho(kernel, s, c2, mu):
    """The GNC surrogate rho_mu(s) (Yang et al. 2020): TLS for mu -> inf, GM at mu = 1."""
    xp = array_module(kernel, s, c2, mu)
    with np.errstate(**_DISCARDED):
        lo, hi = _tls_band(xp, mu, c2)
        tls = xp.where(s <= lo, s, xp.where(s >= hi, c2, 2.0 * xp.sqrt(c2 * mu * (mu + 1.0) * s) - mu * (c2 + s)))
        gm = mu * c2 * s / (mu * c2 + s)
    return xp.where(kernel == TLS, tls, gm)


def gnc_weight(kernel, s, c2, mu):
    """rho_mu'(s): GNC's closed-form weight update (TLS: Yang et al. Eq. (14); GM: Eq. (12))."""
    xp = array_module(kernel, s, c2, mu)
    with np.errstate(**_DISCARDED):
        lo, hi = _tls_band(xp, mu, c2)
        mid = xp.sqrt(c2 * mu * (mu + 1.0) / xp.maximum(s, lo)) - mu
        tls = xp.where(s <= lo, 1.0, xp.where(s >= hi, 0.0, mid))
        gm = (mu * c2 / (s + mu * c2)) ** 2
    return xp.clip(xp.where(kernel == TLS, tls, gm), 0.0, 1.0)


def gnc_initial_mu(kernel, s_max, c2):
    """mu_0: TLS c^2 / (2 s_max - c^2) (rho_mu convex over the residuals); GM 2 s_max / c^2.
    Residuals all within c^2 (nothing to discount): mu_0 = inf (TLS) / 1 (GM), GNC ends at once."""
    xp = array_module(kernel, s_max, c2)
    with np.errstate(**_DISCARDED):
        tls = xp.where(2.0 * s_max > c2, c2 / xp.maximum(2.0 * s_max - c2, 1e-300 * c2), xp.inf)
        gm = xp.maximum(2.0 * s_max / c2, 1.0)
    return xp.where(kernel == TLS, tls, gm)


# ------------------------------------------------------------------------------------------------
# configuration
# ------------------------------------------------------------------------------------------------


class GNCConfig(eqx.Module):
    """Graduated non-convexity (Yang et al. 2020), in stages of the distributed solver.

    ``factor`` (> 1): mu grows (TLS) or shrinks (GM) by this factor per stage (Yang et al.: 1.4).
    A stage ends when the weighted objective changes by less than a relative ``stage_tolerance``
    over one iteration, or after ``stage_iterations``; GNC ends when the weights are binary within
    ``weight_tolerance`` and mu >= ``final_mu`` (TLS: rho_mu is then TLS but for residuals within
    about 10 % of c^2; binary weights at a small mu were seen to end GNC on a wrong solution), when
    mu reaches 1 (GM) or after ``max_stages`` stages; the weights
    then stay fixed and the rest of the budget solves the weighted least squares. Stages solved
    loosely misclassify: on a 200-pose Cube with 50 % outlier loop closures, 30 iterations / 1e-4
    per stage ended GNC at a wrong solution (outlier precision 0.92, ATE 1.5x the outlier-free
    one), 100 / 1e-6 found every outlier and no inlier (ATE equal to the outlier-free one). All fields are
    traced numbers (a new value reuses the compiled code), checked when the config is built.
    """

    factor: float = 1.4
    stage_iterations: int = 100
    stage_tolerance: float = 1e-6
    weight_tolerance: float = 1e-4
    max_stages: int = 200
    final_mu: float = 10.0

    def __check_init__(self):
        owner = "GNCConfig"
        check_real(owner, "factor", self.factor, 1.0, low_open=True)
        check_count(owner, "stage_iterations", self.stage_iterations, 1)
        check_real(owner, "stage_tolerance", self.stage_tolerance, 0.0)
        check_real(owner, "weight_tolerance", self.weight_tolerance, 0.0, 0.5)
        check_count(owner, "max_stages", self.max_stages, 1)
        check_real(owner, "final_mu", self.final_mu, 0.0)


class RobustLoss(eqx.Module):
    """A robust kernel and how its weights are updated (see the module docstring).

    ``kernel``: a name of :data:`LOSSES` (stored as an integer code, a traced leaf: problems with
    different kernels batch together). ``scale``: c in residual units (default
    :func:`chi2_scale` of the graph's dimension, filled in by :meth:`with_defaults`). ``gnc``: a
    :class:`GNCConfig` to run GNC stages in the distributed solver (``tls`` and ``geman-mcclure``;
    the others may not); None otherwise (the default start, GNC-chordal, then does GNC).
    ``update_every`` (K >= 1): M-estimator weights are set
    to rho'(s) every K outer iterations (and at the start); ``max_updates``: at most this many
    updates after the start (None: no bound), after which the weights stay. ``trust_odometry``
    (default True, as dpgo and Kimera-Multi do): edges between consecutive poses (|i - j| = 1,
    odometry) are known inliers, weight 1 and cost s; only the loop closures are robust. This keeps
    every robot's trajectory connected whatever the weights, and GNC's first stages from discarding
    odometry bent by outliers.
    """

    kernel: int
    scale: float | None = None
    gnc: GNCConfig | None = None
    use_gnc: bool = False
    update_every: int = 1
    max_updates: int | None = None
    trust_odometry: bool = eqx.field(static=True, default=True)

    def __init__(self, kernel="huber", scale=None, *, gnc=None, update_every: int = 1, max_updates=None,
                 use_gnc=None, trust_odometry: bool = True):
        self.trust_odometry = bool(trust_odometry)
        code = concrete_value(kernel)
        if code is None or code.dtype.kind in "iu":  # traced or already a code (pytree unflattening)
            self.kernel = kernel if code is None else loss_code(int(code))
            self.scale, self.gnc, self.update_every, self.max_updates = scale, gnc, update_every, max_updates
            self.use_gnc = use_gnc if use_gnc is not None else gnc is not None
            return
        name = str(kernel)
        self.kernel = loss_code(name)
        if gnc is not None and name not in GNC_LOSSES:
            raise ValueError(f"RobustLoss: GNC applies to {' and '.join(GNC_LOSSES)}, not {name!r}")
        self.scale, self.gnc, self.update_every, self.max_updates = scale, gnc, update_every, max_updates
        # GNC runs in the distributed solver only when asked for; otherwise the kernel is a plain
        # M-estimator (weights rho'(s), for TLS 1 up to c^2 and 0 beyond) from its start, and TLS's
        # GNC is done by the default robust start (mmpgo_jax._init.robust_start)
        self.use_gnc = gnc is not None if use_gnc is None else bool(use_gnc)

    def __check_init__(self):
        owner = "RobustLoss"
        if self.scale is not None:
            check_real(owner, "scale", self.scale, 0.0, low_open=True)
        if self.gnc is not None and not isinstance(self.gnc, GNCConfig):
            raise TypeError(f"{owner}.gnc must be a GNCConfig or None, got {type(self.gnc).__name__}")
        check_count(owner, "update_every", self.update_every, 1)
        if self.max_updates is not None:
            check_count(owner, "max_updates", self.max_updates, 0)

    @property
    def name(self) -> str:
        """The kernel's name (concrete codes only)."""
        return LOSSES[int(np.asarray(self.kernel))]

    def with_defaults(self, dim: int) -> RobustLoss:
        """Every optional number filled in (scale: :func:`chi2_scale`; a GNCConfig where GNC is off,
        so that problems with and without GNC share one pytree structure)."""
        return RobustLoss(self.kernel, chi2_scale(dim) if self.scale is None else self.scale,
                          gnc=self.gnc if self.gnc is not None else GNCConfig(), update_every=self.update_every,
                          max_updates=np.iinfo(np.int32).max if self.max_updates is None else self.max_updates,
                          use_gnc=self.use_gnc, trust_odometry=self.trust_odometry)


def as_loss(loss, scale=None, gnc=None, **options) -> RobustLoss | None:
    """``solve``'s ``loss`` / ``loss_scale`` / ``gnc`` as a :class:`RobustLoss`, or None for the plain
    least-squares path (``loss="l2"`` without options keeps today's compiled program bit for bit)."""
    if isinstance(loss, RobustLoss):
        if scale is not None or gnc is not None or options:
            raise ValueError("give the scale and GNC options inside the RobustLoss, not beside it")
        return loss
    name = loss if loss is not None else "l2"
    loss_code(name)
    if name == "l2" and gnc is None and not options:
        if scale is not None:
            check_real("solve", "loss_scale", scale, 0.0, low_open=True)
        return None
    return RobustLoss(name, scale, gnc=gnc, **options)


# ------------------------------------------------------------------------------------------------
# per-step state of the weights (a leaf of MMState)
# ------------------------------------------------------------------------------------------------


class WeightSchedule(eqx.Module):
    """Where the weight updates stand (scalars, replicated over robots).

    ``mu``: GNC's current mu (nan before the first stage ends); ``stage``: GNC stages finished;
    ``stage_iterations``: iterations into the current stage (GNC) or since the last update;
    ``updates``: weight updates after the start; ``done``: the weights no longer change;
    ``weighted_f``: 2 x the weighted objective 1/2 sum w s at the current iterate (GNC's stage test);
    ``held``: the start's given weights are still held (a first stage, see :func:`next_weights`).
    """

    mu: jax.Array
    stage: jax.Array
    stage_iterations: jax.Array
    updates: jax.Array
    done: jax.Array
    weighted_f: jax.Array
    held: jax.Array


def initial_schedule(loss: RobustLoss, weighted_f, held=False) -> WeightSchedule:
    dt = jnp.asarray(weighted_f).dtype
    zero = jnp.zeros((), jnp.int32)
    held = jnp.asarray(held, bool)
    return WeightSchedule(mu=jnp.full((), jnp.nan, dt), stage=zero, stage_iterations=zero, updates=zero,
                          done=jnp.asarray(loss.kernel == L2) & ~held, weighted_f=jnp.asarray(weighted_f, dt),
                          held=held)


def next_weights(loss: RobustLoss, sched: WeightSchedule, s, weights, weighted_f, s_max, total, robust_edge):
    """(update?, new weights, new schedule) after an iteration that ended at residuals ``s``
    ((A, e) incident edges; ``robust_edge`` (A, e) the edges the loss applies to, the others keep
    weight 1; ``s_max`` the maximum of s over those edges of all robots, ``weighted_f`` the weighted
    objective with the current weights, ``total`` the sum over all robots). Every robot decides
    alike (the inputs are global), and an edge held by two robots has the same residual on both
    sides, so it gets the same weight on both.

    Weights given with the start (``sched.held``) are held as a first stage: until the weighted
    objective stalls by GNC's stage rule (``GNCConfig.stage_tolerance`` / ``stage_iterations``), the
    run solves the weighted least squares of the start's classification; then the loss's own rule
    takes over (an M-estimator: rho'(s) at that point, every ``update_every`` iterations; GNC: its
    first stage's weights at mu_0 of the residuals there). A start that keeps the maps rigid (the
    distributed robust start) leaves correct inter-robot closures with residuals far above c^2;
    weighting them by rho'(s) at X^0 would reject them all."""
    c2 = jnp.asarray(loss.scale, s.dtype) ** 2
    k = sched.stage_iterations + 1
    gnc = loss.gnc
    # M-estimators: every K iterations, at most max_updates times
    # GNC (and a held start): a stage ends on a stalled weighted objective or its budget
    change = jnp.abs(sched.weighted_f - weighted_f)
    stalled = change <= gnc.stage_tolerance * jnp.abs(sched.weighted_f)
    stage_end = stalled | (k >= gnc.stage_iterations)
    m_update = jnp.where(sched.held, stage_end, (k >= loss.update_every) & (sched.updates < loss.max_updates))
    use_gnc = jnp.asarray(loss.use_gnc)
    update = ~sched.done & jnp.where(use_gnc, stage_end, m_update)
    mu = jnp.where(jnp.isnan(sched.mu), gnc_initial_mu(loss.kernel, s_max, c2), sched.mu)
    w_gnc = gnc_weight(loss.kernel, s, c2, mu)
    w_new = jnp.where(use_gnc, w_gnc, weight(loss.kernel, s, c2))
    between = robust_edge & (w_gnc > gnc.weight_tolerance) & (w_gnc < 1.0 - gnc.weight_tolerance)
    binary = total(jnp.sum(between, axis=tuple(range(1, between.ndim)))) == 0
    mu_next = jnp.where(loss.kernel == TLS, mu * gnc.factor, jnp.maximum(mu / gnc.factor, 1.0))
    tls_over = (binary & (mu >= gnc.final_mu)) | jnp.isinf(mu)
    gnc_over = jnp.where(loss.kernel == TLS, tls_over, mu <= 1.0) | (sched.stage + 1 >= gnc.max_stages)
    m_over = (sched.updates + 1 >= loss.max_updates) | (loss.kernel == L2)
    done = sched.done | (update & jnp.where(use_gnc, gnc_over, m_over))
    new = WeightSchedule(
        mu=jnp.where(update & use_gnc, mu_next, sched.mu),
        stage=sched.stage + (update & use_gnc).astype(jnp.int32),
        stage_iterations=jnp.where(update, 0, k),
        updates=sched.updates + update.astype(jnp.int32),
        done=done,
        weighted_f=weighted_f,
        held=sched.held & ~update,
    )
    return update, jnp.where(update & robust_edge, w_new, weights), new


def start_weights(loss: RobustLoss, s, robust_edge, given=None, use_given=False):
    """Weights at X^0: ``given`` where ``use_given`` (weights that came with the start, held as a first
    stage, see :func:`next_weights`), else rho'(s) for an M-estimator and 1 for GNC (its first stage
    is least squares); 1 on the edges outside ``robust_edge``."""
    c2 = jnp.asarray(loss.scale, s.dtype) ** 2
    w = jnp.where(jnp.asarray(loss.use_gnc), jnp.ones_like(s), weight(loss.kernel, s, c2))
    if given is not None:
        w = jnp.where(use_given, jnp.asarray(given, s.dtype), w)
    return jnp.where(robust_edge, w, 1.0)


def robust_cost(loss: RobustLoss, s, robust_edge):
    """rho_c(s) per edge (the f = 2F_rho convention; s outside ``robust_edge``); GNC kernels report
    their final kernel."""
    c2 = jnp.asarray(loss.scale, s.dtype) ** 2
    return jnp.where(robust_edge, rho(loss.kernel, s, c2), s)


def robust_edges(loss: RobustLoss, graph_i, graph_j) -> np.ndarray:
    """(m,) bool: the edges the loss applies to (all, or all but odometry with ``trust_odometry``)."""
    gi, gj = np.asarray(graph_i, np.int64), np.asarray(graph_j, np.int64)
    return np.abs(gi - gj) != 1 if loss.trust_odometry else np.ones(len(gi), bool)


# ------------------------------------------------------------------------------------------------
# host side: per-robot incident edges <-> the graph's edges
# ------------------------------------------------------------------------------------------------


def incident_edge_index(graph_i, graph_j, robot_of_pose, num_robots: int, max_edges: int) -> np.ndarray:
    """(A, e_max) index of the graph edge held in each incident-edge slot of
    :func:`~mmpgo_jax.partition` (-1 on padding): each robot's list is its tail edges in edge
    order, then the inter-robot edges whose head it owns (the layout ``partition`` builds)."""
    rop = np.asarray(robot_of_pose)
    gi, gj = np.asarray(graph_i), np.asarray(graph_j)
    ri, rj = rop[gi], rop[gj]
    inter = ri != rj
    owner = np.concatenate([ri, rj[inter]])
    edge = np.concatenate([np.arange(len(gi)), np.flatnonzero(inter)])
    order = np.argsort(owner, kind="stable")
    owner, edge = owner[order], edge[order]
    counts = np.bincount(owner, minlength=num_robots)
    slot = np.arange(len(owner)) - np.repeat(np.concatenate([[0], np.cumsum(counts)[:-1]]), counts)
    out = np.full((num_robots, max_edges), -1, np.int64)
    out[owner, slot] = edge
    return out


def robust_outcome(loss: RobustLoss, graph, partition, weights, poses):
    """(weights, inliers), each (m,) in the graph's edge order, of a robust run that ended with the
    incident-edge ``weights`` (A, e_max) of ``partition`` at ``poses`` (global order, any frame):
    the weights of the last majorizer and the edges whose residual is within the scale, s <= c^2
    (for TLS after GNC: the edges of weight 1)."""
    index = incident_edge_index(graph.i, graph.j, partition.robot_of_pose, partition.num_robots,
                                partition.max_edges)
    w = edge_values(np.asarray(weights), index, graph.num_edges)
    s = host_edge_costs(graph, poses)
    return w, (s <= float(np.asarray(loss.scale)) ** 2) | ~robust_edges(loss, graph.i, graph.j)


def robust_objective(loss: RobustLoss, graph, poses) -> float:
    """f = 2 F_rho = sum of rho_c(s) over the loss's edges plus s over the others, at ``poses``
    (global order, any frame), computed on the host: the number two robust runs of one graph are
    compared by."""
    s = host_edge_costs(graph, poses)
    c2 = float(np.asarray(loss.scale)) ** 2
    costs = np.where(robust_edges(loss, graph.i, graph.j), rho(int(np.asarray(loss.kernel)), s, c2), s)
    return float(np.sum(costs))


def edge_values(per_slot, index: np.ndarray, num_edges: int) -> np.ndarray:
    """Per-graph-edge values from per-incident-slot values (A, e_max) (an inter-robot edge is held
    by two robots; they agree, see :func:`next_weights`; the tail robot's copy is taken)."""
    per_slot = np.asarray(per_slot)
    out = np.full(num_edges, np.nan, per_slot.dtype if per_slot.dtype.kind == "f" else np.float64)
    real = index >= 0
    # reversed so that the first copy (the tail robot's) is written last and kept
    out[index[real][::-1]] = per_slot[real][::-1]
    return out
