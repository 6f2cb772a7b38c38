"""Registry of the standard PGO benchmarks and resolution of the data directory.

The registry lives in ``mmpgo_jax/benchmarks.json`` (package data) and holds, for every benchmark
of the paper's Tables I/II and the extras shipped by SE-Sync: dimensions, provenance, the paper's
printed numbers (f*, and f after 100/250/1000 iterations with 10 robots for MM, AMM and DGS), the
certified SE-Sync optimum, f at the centralized chordal initialization and the measurements of the
authors' C++ code.  All objective values are f = 2F.  Where each number comes from (the paper,
SE-Sync, the authors' code, or measured here and how) is ``docs/conventions.md`` in the
repository: §2 for f = 2F, §5 for ``chordal_f``, §6 for ``sesync_fstar``, §7 for the ``code_*``
fields.

The benchmark files themselves are not part of the package.  They are looked up in, by
precedence: an explicit directory (``data=`` / the CLI's ``--data``), the environment variable
``MMPGO_DATA``, and ``<repo>/../shared/datasets`` when it exists (repo = the folder holding the
``mmpgo_jax`` package).  See ``datasets/README.md`` in the repository.

Names and paths are never substituted for one another (:func:`find_benchmark`): an argument with
a directory part, starting with ``~`` or ``.``, or existing in the file system is a path and only
that; only a bare name (a registered benchmark or a file name absent from the working directory)
is looked up in the data folder.
"""

from __future__ import annotations

import json
import os
import re
from collections.abc import Mapping
from dataclasses import dataclass, field
from importlib import resources
from pathlib import Path
from types import MappingProxyType

from .._core.messages import join_items

__all__ = [
    "BENCHMARKS",
    "ENV_VAR",
    "BenchmarkInfo",
    "DatasetNotFoundError",
    "FStarReference",
    "available_benchmarks",
    "benchmark_info",
    "data_dir",
    "find_benchmark",
    "names_a_path",
]

ENV_VAR = "MMPGO_DATA"
_PACKAGE_DIR = Path(__file__).resolve().parents[1]  # mmpgo_jax/
_REPO_DIR = _PACKAGE_DIR.parent
_DEFAULT_DIR = _REPO_DIR.parent / "shared" / "datasets"

IterTable = Mapping[int, float]


@dataclass(frozen=True)
class FStarReference:
    """The optimum a relative gap (f - f*)/|f*| is measured against, and where it comes from:
    ``"certified"`` (this project's f*, certified globally optimal, 12 digits), ``"sesync"``
    (SE-Sync's published value, rounded), ``"paper"`` (Tables I/II, 4 digits) or
    ``"uncertified"`` (a centralized solve the certificate did not confirm)."""

    value: float
    source: str

    LABELS = MappingProxyType({"certified": "certified f*", "sesync": "published f* (SE-Sync, rounded)",
                               "paper": "published f* (paper, 4 digits)",
                               "uncertified": "uncertified f* (centralized solve)"})

    @property
    def label(self) -> str:
        """E.g. "certified f*": what a printed gap says it is measured against."""
        return self.LABELS.get(self.source, f"f* ({self.source})")

    def gap(self, f):
        """(f - f*)/|f*| (elementwise for arrays)."""
        return (f - self.value) / abs(self.value)


@dataclass(frozen=True)
class BenchmarkInfo:
    """One benchmark: metadata and reference numbers (f = 2F convention throughout).

    Iteration tables (``paper_mm``, ``code_mm``, ...) map 100 / 250 / 1000 to f after that many
    iterations with 10 robots, or are ``None`` where no number exists.
    """

    name: str  # the paper's name ("MITb"); extras use the file stem
    file: str  # file name ("MIT.g2o")
    dim: int
    num_poses: int  # n = max id + 1
    num_edges: int
    source: str
    paper_fstar: float | None = None  # Table I/II f*, as printed (4 significant digits)
    sesync_fstar: float | None = None  # certified SE-Sync optimum (docs/conventions.md §6)
    chordal_f: float | None = None  # f at the centralized chordal initialization (docs/conventions.md §5)
    paper_mm: IterTable | None = None  # Table I/II, MM-PGO
    paper_amm: IterTable | None = None  # Table I/II, AMM-PGO
    in_paper: bool = False
    paper_dgs: IterTable | None = None  # Table I/II, DGS [11]
    paper_table: str | None = None  # "I" (2D) or "II" (3D)
    code_mm: IterTable | None = None  # authors' C++ MM (docs/conventions.md §7)
    code_amm_paper_rule: IterTable | None = None  # their AMM with Algorithm 2's test (conventions §7)
    code_amm_adaptive: IterTable | None = None  # their AMM with its adaptive restart (conventions §7)
    # ms per outer iteration of their MM / AMM (10 robots, one thread), measured 2026-12-01 (conventions §7)
    code_ms_per_iter_mm: float | None = None
    code_ms_per_iter_amm: float | None = None
    code_iters_to_1e_3: int | None = None  # their adaptive AMM's iterations to rel. gap 1e-3 (conventions §7)
    availability: str = "shipped"  # "shipped" | "public" (obtainable, not shipped) | "unavailable"
    # this project's optimum: centralized_optimum, 12 digits, and its certificate (benchmarks/certified_optimum.py)
    ours_fstar: float | None = None
    ours_certificate: Mapping | None = None
    notes: str = ""
    aliases: tuple[str, ...] = field(default=(), compare=False)

    def __hash__(self) -> int:  # the dict-valued fields are not hashable
        return hash((self.name, self.file))

    @property
    def certified_fstar(self) -> float | None:
        """This project's f* (12 digits) where SE-Sync's dual certificate proved it the global optimum."""
        certified = bool(self.ours_certificate and self.ours_certificate.get("certified"))
        return self.ours_fstar if certified else None

    @property
    def fstar_references(self) -> tuple[FStarReference, ...]:
        """Every optimum the registry holds, best first: :attr:`certified_fstar`, SE-Sync's
        published value, the paper's printed one (both rounded)."""
        values = (("certified", self.certified_fstar), ("sesync", self.sesync_fstar), ("paper", self.paper_fstar))
        return tuple(FStarReference(float(v), source) for source, v in values if v is not None)

    @property
    def fstar_reference(self) -> FStarReference | None:
        """The reference of every relative gap: the first of :attr:`fstar_references`, or None."""
        refs = self.fstar_references
        return refs[0] if refs else None

    @property
    def fstar(self) -> float | None:
        """Best known optimum (the value of :attr:`fstar_reference`)."""
        ref = self.fstar_reference
        return None if ref is None else ref.value

    def path(self, data: str | os.PathLike | None = None) -> Path:
        """Location of this benchmark's file in the data folder (raises :class:`DatasetNotFoundError`)."""
        return _find_in_data(self.file, data)


class DatasetNotFoundError(FileNotFoundError):
    """A benchmark file could not be found (the message says where to look and how to get it)."""


def _iter_table(d) -> IterTable | None:
    if d is None:
        return None
    return MappingProxyType({int(k): float(v) for k, v in d.items()})


def _load_registry() -> dict[str, BenchmarkInfo]:
    text = resources.files("mmpgo_jax").joinpath("benchmarks.json").read_text(encoding="utf-8")
    doc = json.loads(text)
    out: dict[str, BenchmarkInfo] = {}
    tables = ("paper_mm", "paper_amm", "paper_dgs", "code_mm", "code_amm_paper_rule",
              "code_amm_adaptive")
    for row in doc["benchmarks"]:
        row = dict(row)
        if row.get("ours_certificate") is not None:
            row["ours_certificate"] = MappingProxyType(dict(row["ours_certificate"]))
        for key in tables:
            row[key] = _iter_table(row.get(key))
        stem = row["file"].rsplit(".", 1)[0]
        row["aliases"] = tuple(dict.fromkeys(a.lower() for a in (row["name"], row["file"], stem)))
        info = BenchmarkInfo(**row)
        if info.name in out:
            raise ValueError(f"duplicate benchmark name {info.name!r} in benchmarks.json")
        out[info.name] = info
    return out


BENCHMARKS: Mapping[str, BenchmarkInfo] = MappingProxyType(_load_registry())

_ALIASES: dict[str, BenchmarkInfo] = {}
for _info in BENCHMARKS.values():
    for _a in _info.aliases:
        if _a in _ALIASES and _ALIASES[_a] is not _info:
            raise ValueError(f"benchmark alias {_a!r} is ambiguous")
        _ALIASES[_a] = _info
del _info, _a


def benchmark_info(name_or_file: str) -> BenchmarkInfo | None:
    """Registry entry for a paper name, file name or file stem (case-insensitive), else None.

    ``"MITb"``, ``"MIT"``, ``"mit.g2o"`` all give the MITb entry; a path's directory is ignored.
    """
    key = os.path.basename(str(name_or_file).strip()).lower()
    return _ALIASES.get(key)


def data_dir(explicit: str | os.PathLike | None = None) -> Path | None:
    """The benchmark data folder: ``explicit`` > ``$MMPGO_DATA`` > ``<repo>/../shared/datasets``.

    The first two are returned as given (expanded, not checked); the default only when it
    exists.  ``None`` when nothing is configured.
    """
    if explicit is not None and str(explicit) != "":
        return Path(explicit).expanduser()
    env = os.environ.get(ENV_VAR, "").strip()
    if env:
        return Path(env).expanduser()
    if _DEFAULT_DIR.is_dir():
        return _DEFAULT_DIR
    return None


def _lookup_in(directory: Path, filename: str) -> Path | None:
    """``directory / filename``, matching the file name case-insensitively."""
    cand = directory / filename
    try:
        if cand.is_file():
            return cand
    except OSError:  # e.g. a name too long for the file system: not there
        return None
    if not directory.is_dir():
        return None
    low = filename.lower()
    for p in sorted(directory.iterdir()):
        if p.name.lower() == low and p.is_file():
            return p
    return None


def _where(directory: Path | None, explicit) -> str:
    if directory is None:
        return f"no data folder is configured (${ENV_VAR} is unset and the default {_DEFAULT_DIR} does not exist)"
    if explicit is not None and str(explicit) != "":
        how = "--data"
    elif os.environ.get(ENV_VAR, "").strip():
        how = f"${ENV_VAR}"
    else:
        how = "the default"
    state = "" if directory.is_dir() else "; it does not exist"
    return f"searched {directory} ({how}{state})"


def _holds(directory: Path | None) -> str:
    """What the data folder holds: " (it holds a.g2o, b.g2o and 9 more)", or "" if it is not there."""
    try:
        files = sorted((p.name for p in directory.iterdir() if p.suffix.lower() == ".g2o"), key=str.lower)
    except (AttributeError, OSError):  # no folder configured, or not readable
        return ""
    return f" (it holds {join_items(files, 70)})" if files else " (it holds no .g2o file)"


def names_a_path(query: str | os.PathLike) -> bool:
    """Whether a file argument is a path (and nothing else) rather than a benchmark name.

    A path has a directory part (contains ``/`` or the OS separator), starts with ``~`` or ``.``,
    or exists in the file system (relative to the working directory).  Everything else is a bare
    name, looked up in the data folder.
    """
    text = os.fspath(query)
    if not isinstance(text, str):
        text = os.fsdecode(text)
    seps = {"/", os.sep} | ({os.altsep} if os.altsep else set())
    if any(sep in text for sep in seps) or text.startswith(("~", ".")):
        return True
    return text != "" and os.path.lexists(text)


def find_benchmark(name_or_file: str | os.PathLike, data: str | os.PathLike | None = None) -> Path:
    """Path of a g2o file given as a path or as a benchmark name; never substitutes one for the other.

    * A path (see :func:`names_a_path`: it has a directory part, starts with ``~`` or ``.``, or
      exists) is returned as given (``~`` expanded) if it is a file; otherwise
      :class:`DatasetNotFoundError` ("PATH: file not found") or :class:`IsADirectoryError`
      ("PATH: is a directory, not a g2o file") is raised.  The data folder is not consulted.
    * A bare name is looked up in the data folder :func:`data_dir(data) <data_dir>`: the paper's
      name, the file name or its stem of a registered benchmark, case-insensitively ("MITb",
      "MIT", "mit.g2o", "garage"), or any other file name present there (with or without
      ``.g2o``).  If it is not there, :class:`DatasetNotFoundError` says which folder was searched,
      how to configure it and where the file can be obtained.
    """
    query = os.fspath(name_or_file)
    if not isinstance(query, str):
        query = os.fsdecode(query)
    if names_a_path(query):
        path = Path(query).expanduser()
        if path.is_dir():
            raise IsADirectoryError(f"{query}: is a directory, not a g2o file")
        if not path.exists():
            raise DatasetNotFoundError(f"{query}: file not found")
        return path
    return _find_in_data(query.strip(), data)


def _find_in_data(query: str, data: str | os.PathLike | None) -> Path:
    """``query`` (a bare benchmark name or file name) in the data folder."""
    directory = data_dir(data)
    info = benchmark_info(query)
    names = [info.file] if info is not None else [query, query + ".g2o"]
    if directory is not None:
        for fname in names:
            hit = _lookup_in(directory, os.path.basename(fname))
            if hit is not None:
                return hit

    configure = f"set ${ENV_VAR} or --data (data= in Python) to a folder holding it"
    if info is not None:
        label = info.file if info.name == info.file.rsplit(".", 1)[0] else f"{info.file} (\"{info.name}\")"
        # the source's clause with the link, short commit hashes (the full text: datasets/README.md)
        clauses = info.source.split("; ")
        source = next((c for c in clauses if "://" in c), clauses[0])
        source = re.sub(r"\b([0-9a-f]{7})[0-9a-f]{33}\b", r"\1", source)
        source = re.sub(r" \((also|git blob) [^)]*\)", "", source)
        msg = [f"benchmark file {label} not found: {_where(directory, data)}; {configure}.",
               f"Source: {source}" + (" (not available here)." if info.availability == "unavailable"
                                      else ".")]
    else:
        registered = join_items(sorted(BENCHMARKS, key=str.lower), 70)
        msg = [f"{query!r} is neither a file here nor a registered benchmark: {_where(directory, data)}"
               f"{_holds(directory)}; registered: {registered}."]
    raise DatasetNotFoundError(" ".join(msg))


def available_benchmarks(data: str | os.PathLike | None = None) -> list[BenchmarkInfo]:
    """Registry entries whose file is present in the data folder (registry order)."""
    directory = data_dir(data)
    if directory is None or not directory.is_dir():
        return []
    return [info for info in BENCHMARKS.values() if _lookup_in(directory, info.file) is not None]
