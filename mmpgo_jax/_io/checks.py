"""The reader's value checks: converted lines -> checked quaternions, information and weights.

Every check is vectorised over the lines of one tag and reports only its first failing line, as
``(line, "TAG: problem")``; the reader raises the earliest line over all checks as one
:class:`~mmpgo_jax._io.format.G2OFormatError` naming file, line and problem. A line that failed a
check is left out of the later ones (their values would be meaningless there), so each line is
reported for its first problem, in the order of :func:`_check_values`. The rules are those of
:mod:`mmpgo_jax._io.g2o`'s docstring.
"""

from __future__ import annotations

import math
import re
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from .format import (
    _TORO_INFO_SCALE,
    INFORMATION_MAX,
    INFORMATION_MIN,
    QUATERNION_NORM_MIN,
    WEIGHT_MAX,
    WEIGHT_MIN,
    _Format,
    _info_size,
    _upper_to_full,
)
from .tokens import _NUMBER_RE, _first, _Group, _parse_id, _show
from .weights import sesync_weights


@dataclass(frozen=True)
class _Limits:
    """What the float dtype of the result can represent (squared residuals, weights)."""

    dtype_name: str
    square_max: float  # |t|^2 and tau |t|^2 must not exceed this
    weight_min: float
    weight_max: float

    @staticmethod
    def of(dtype) -> _Limits:
        fi = np.finfo(dtype)
        return _Limits(
            np.dtype(dtype).name,
            float(fi.max),
            max(WEIGHT_MIN, float(fi.tiny)),
            min(WEIGHT_MAX, float(fi.max)),
        )


def _g(x) -> str:
    return f"{float(x):.6g}"


def _scaled(fmt: _Format, v: int) -> str:
    """A note for messages on TORO 3D information entries, which are checked after scaling."""
    if not fmt.euler or not fmt.is_edge or _TORO_INFO_SCALE[v - fmt.information_start] == 1:
        return ""
    return f" (after scaling by {_TORO_INFO_SCALE[v - fmt.information_start]:g} to g2o's quaternion coordinates)"


class _Report:
    """One group's failed checks: the first failing line of each check goes to ``problems``, and all
    failing lines leave ``ok`` (the lines later checks still look at)."""

    def __init__(self, group: _Group, problems: list):
        self.group, self.problems, self.ok = group, problems, group.ok

    def __call__(self, bad: np.ndarray, message: Callable[[int], str]) -> None:
        bad = bad & self.ok
        r = _first(bad)
        if r is not None:
            self.problems.append((self.group.lines[r], f"{self.group.fmt.tag}: {message(r)}"))
            self.ok = self.ok & ~bad  # later checks are meaningless on such rows

    def name(self, v: int) -> str:
        """The field name of value ``v`` of the g2o layout."""
        fmt = self.group.fmt
        return fmt.fields[fmt.field_of(v)]

    def token(self, r: int, v: int) -> bytes:
        """The file's text of value ``v`` (g2o layout) of row ``r``."""
        return self.group.rows[r][self.group.fmt.field_of(v)]


def _check_finite(report: _Report, vals: np.ndarray) -> np.ndarray:
    """Refuse non-finite values (overflowing numbers are "out of range"); the values in the g2o layout."""
    group = report.group
    fmt, nid = group.fmt, group.fmt.num_ids
    finite = np.isfinite(vals)

    def message(r: int) -> str:
        v = int(np.flatnonzero(~finite[r])[0])  # in the file's layout
        tok = group.rows[r][v + nid]
        if _NUMBER_RE.fullmatch(tok):
            return (f"field {v + nid + 1} ({fmt.fields[v + nid]}) is out of range (its magnitude overflows "
                    f"float64): {_show(tok)}")
        return f"field {v + nid + 1} ({fmt.fields[v + nid]}) is not finite: {float(vals[r, v])!r}"

    report(~finite.all(axis=1), message)
    return fmt.to_g2o(np.where(report.ok[:, None], vals, 0.0))


def _check_quaternions(report: _Report, vals: np.ndarray) -> np.ndarray:
    """Normalise (x, y, z, w) without overflow or underflow: divide by the largest |component|, then
    by the norm; refuse a norm below QUATERNION_NORM_MIN. Returns the unit quaternions."""
    q = vals[:, 3:7]
    scale = np.abs(q).max(axis=1)
    qs = q / np.where(scale > 0, scale, 1.0)[:, None]
    qn = np.sqrt(np.einsum("ka,ka->k", qs, qs))  # in [1, 2] when scale > 0
    qnorm = scale * qn
    report(
        ~(qnorm >= QUATERNION_NORM_MIN),
        lambda r: (
            f"quaternion (qx, qy, qz, qw) has zero norm "
            f"(|q| = {qnorm[r]:.3g} < {QUATERNION_NORM_MIN:g}), cannot be normalised"
        ),
    )
    return qs / np.where(qn > 0, qn, 1.0)[:, None]


def _too_large(report: _Report, t: np.ndarray, limits: _Limits) -> Callable[[int, str], str]:
    """The message of a translation whose weighted or plain squared norm overflows (left open for
    the caller to add what else to say, and close the parenthesis)."""
    fmt = report.group.fmt
    names = ", ".join(fmt.fields[fmt.num_ids : fmt.num_ids + fmt.dim])

    def message(r: int, what: str) -> str:
        return (
            f"translation ({names}) is too large: {what} overflows {limits.dtype_name} "
            f"(|t| = {math.hypot(*t[r].tolist()):.3g}"
        )

    return message


def _check_information_entries(report: _Report, upper: np.ndarray) -> None:
    """A positive diagonal, and every nonzero entry within [INFORMATION_MIN, INFORMATION_MAX]."""
    fmt = report.group.fmt
    ksz, start = _info_size(fmt.dim), fmt.information_start
    diag_pos = np.array([v for v, (r, c) in enumerate(zip(*np.triu_indices(ksz), strict=True)) if r == c])
    diag = upper[:, diag_pos]

    def diag_message(r: int) -> str:
        c = int(np.flatnonzero(~(diag[r] > 0))[0])
        v = start + int(diag_pos[c])
        mantissa = report.token(r, v).lower().split(b"e")[0]
        under = " (it underflows to 0)" if diag[r, c] == 0 and re.search(rb"[1-9]", mantissa) else ""
        return (
            f"information matrix is not positive definite: diagonal entry {report.name(v)} = "
            f"{float(diag[r, c])!r} is not positive{under}{_scaled(fmt, v)}"
        )

    report(~(diag > 0).all(axis=1), diag_message)
    mag = np.abs(upper)
    small = (mag != 0) & (mag < INFORMATION_MIN)
    large = mag > INFORMATION_MAX

    def range_message(r: int) -> str:
        c = int(np.flatnonzero(small[r] | large[r])[0])
        x = float(upper[r, c])
        if small[r, c]:
            why = f"is nonzero but below {INFORMATION_MIN:g} in magnitude (subnormal or underflowing)"
        else:
            why = (f"is above {INFORMATION_MAX:g} in magnitude (the weights or the weighted squared residuals "
                   "overflow)")
        return f"information entry {report.name(start + c)} = {x!r} {why}{_scaled(fmt, start + c)}"

    report((small | large).any(axis=1), range_message)


def _positive_definite(report: _Report, info: np.ndarray, strict: bool) -> np.ndarray:
    """Which matrices are positive definite (smallest eigenvalue > k eps |largest|); with ``strict``
    the others are refused, else only counted (SE-Sync's convention accepts them)."""
    ksz = info.shape[-1]
    eig = np.linalg.eigvalsh(info)
    tol = ksz * np.finfo(np.float64).eps * np.abs(eig).max(axis=1)
    not_pd = ~(eig[:, 0] > tol)
    if strict:
        report(
            not_pd,
            lambda r: (
                f"information matrix is not positive definite "
                f"(eigenvalues {np.array2string(eig[r], precision=4, separator=', ')})"
            ),
        )
    return ~not_pd


def _check_weight(report: _Report, weight, bad_inverse, symbol: str, formula: str, block: str,
                  limits: _Limits) -> None:
    """An SE-Sync weight: its block inverted, and the weight positive and representable."""
    report(
        bad_inverse,
        lambda r: (
            f"the block {block} of the information matrix is singular or its inverse is not "
            f"representable (not positive definite): {symbol} = {formula} is undefined"
        ),
    )
    report(
        ~(weight > 0),
        lambda r: (
            f"SE-Sync weight {symbol} = {formula} = {_g(weight[r])} is not positive "
            f"(the information matrix is not positive definite)"
        ),
    )
    report(
        ~((weight >= limits.weight_min) & (weight <= limits.weight_max)),
        lambda r: (
            f"SE-Sync weight {symbol} = {formula} = {_g(weight[r])} is not representable: weights "
            f"must be finite and between {limits.weight_min:g} and {limits.weight_max:g} "
            f"({limits.dtype_name})"
        ),
    )


def _check_edge_information(report: _Report, vals: np.ndarray, tn2: np.ndarray, t: np.ndarray, strict: bool,
                            limits: _Limits) -> None:
    """An edge's information matrix and SE-Sync weights (and tau |t|^2); fills the group's ``info``,
    ``kappa``, ``tau`` and ``pd``."""
    group, d = report.group, report.group.fmt.dim
    ksz = _info_size(d)
    upper = vals[:, group.fmt.information_start:]
    _check_information_entries(report, upper)
    info = _upper_to_full(np.where(report.ok[:, None], upper, 0.0), ksz)
    info[~report.ok] = np.eye(ksz)
    pd = _positive_definite(report, info, strict)
    tau, bad_t, kappa, bad_k = sesync_weights(info, d)
    _check_weight(report, tau, bad_t, "tau", f"{d} / tr(inv(I[:{d}, :{d}]))", f"I[:{d}, :{d}]", limits)
    if d == 2:
        _check_weight(report, kappa, bad_k, "kappa", "I33", "I33", limits)
    else:
        _check_weight(report, kappa, bad_k, "kappa", "3 / (2 tr(inv(I[3:, 3:])))", "I[3:, 3:]", limits)
    wt = tau * tn2
    too_large = _too_large(report, t, limits)
    report(
        ~(wt <= limits.square_max),
        lambda r: too_large(r, f"tau |t|^2 = {wt[r]:.3g}") + f", tau = {_g(tau[r])})",
    )
    group.info, group.kappa, group.tau, group.pd = info, kappa, tau, pd


def _check_values(group: _Group, problems: list, strict: bool, limits: _Limits) -> None:
    """Value checks of one group (vectorised); fills the group's quaternions, weights, ...

    In each line the checks run in this order and only the first failure is reported: finite
    values, self-loop, quaternion norm, |t|^2, information diagonal, information entry range,
    positive definiteness (``strict`` only), translation-block inverse and tau, rotation-block
    inverse and kappa, tau |t|^2.
    """
    fmt = group.fmt
    d = fmt.dim
    if group.vals.shape[0] == 0:
        ksz = _info_size(d)
        group.quat, group.tn2, group.info = np.zeros((0, 4)), np.zeros(0), np.zeros((0, ksz, ksz))
        group.kappa, group.tau, group.pd = np.zeros(0), np.zeros(0), np.ones(0, dtype=bool)
        return
    report = _Report(group, problems)
    with np.errstate(all="ignore"):
        vals = group.vals = _check_finite(report, group.vals)
        if fmt.is_edge:
            report(group.ids[:, 0] == group.ids[:, 1], lambda r: f"self-loop edge (i == j == {group.ids[r, 0]})")
        if d == 3:
            group.quat = _check_quaternions(report, vals)
        # translations: the squared norm must be representable
        t = vals[:, :d]
        tn2 = group.tn2 = np.einsum("ka,ka->k", t, t)
        too_large = _too_large(report, t, limits)
        report(~(tn2 <= limits.square_max), lambda r: too_large(r, f"|t|^2 = {tn2[r]:.3g}") + ")")
        if fmt.is_edge:
            _check_edge_information(report, vals, tn2, t, strict, limits)
    group.ok = report.ok


def _check_duplicate_ids(vg: _Group, problems: list) -> None:
    """A VERTEX id defined twice (among the lines that passed their checks)."""
    vid = vg.ids[:, 0]
    okr = np.flatnonzero(vg.ok)
    _, first_row, inv = np.unique(vid[okr], return_index=True, return_inverse=True)
    dup = _first(first_row[inv] != np.arange(okr.shape[0]))  # the first repeat among the checked rows
    if dup is not None:
        r, r0 = int(okr[dup]), int(okr[first_row[inv[dup]]])
        problems.append(
            (vg.lines[r], f"duplicate {vg.fmt.tag} id {int(vid[r])} (already defined on line {vg.lines[r0]})")
        )


def _check_vertex_residuals(eg: _Group, vg: _Group, problems: list, limits: _Limits) -> None:
    """A VERTEX translation t must keep tau |t|^2 representable for every edge at that vertex."""
    vok = np.flatnonzero(vg.ok)
    eok = np.flatnonzero(eg.ok)
    if not vok.size or not eok.size:
        return
    vid = vg.ids[vok, 0]
    order = np.argsort(vid, kind="stable")
    svid = vid[order]
    worst: tuple[int, int, int] | None = None  # (vertex line, vertex row, edge row)
    with np.errstate(all="ignore"):
        for end in (0, 1):
            e_ids = eg.ids[eok, end]
            pos = np.minimum(np.searchsorted(svid, e_ids), svid.size - 1)
            found = svid[pos] == e_ids
            vrow = vok[order[pos]]
            bad = found & ~(eg.tau[eok] * vg.tn2[vrow] <= limits.square_max)
            if bad.any():
                b = np.flatnonzero(bad)
                best = b[np.argmin(np.asarray(vg.lines)[vrow[b]])]
                cand = (vg.lines[vrow[best]], int(vrow[best]), int(eok[best]))
                worst = cand if worst is None or cand[0] < worst[0] else worst
    if worst is None:
        return
    line, r, e = worst
    d = vg.fmt.dim
    t = vg.vals[r, :d]
    names = ", ".join(vg.fmt.fields[1 : 1 + d])
    tau = float(eg.tau[e])
    problems.append(
        (
            line,
            (
                f"{vg.fmt.tag}: translation ({names}) is too large: tau |t|^2 = {tau * float(vg.tn2[r]):.3g} "
                f"overflows {limits.dtype_name} for the edge on line {eg.lines[e]} "
                f"(|t| = {math.hypot(*t.tolist()):.3g}, tau = {_g(tau)})"
            ),
        )
    )


def _fix_ids(fix_lines: list, problems: list) -> list[tuple[int, list[int]]]:
    """The ids of each FIX line, up to its first malformed field (reported)."""
    fix_ids: list[tuple[int, list[int]]] = []
    for lineno, toks in fix_lines:
        ids = []
        for f, tok in enumerate(toks):
            v = _parse_id(tok)
            if isinstance(v, str):
                problems.append((lineno, f"FIX: field {f + 1} {v}"))
                break
            ids.append(v)
        fix_ids.append((lineno, ids))
    return fix_ids
