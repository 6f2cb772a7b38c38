"""Every CPU core for one solve: one JAX CPU device per core, the robots split over them.

XLA runs one CPU device's program on one core for the solver's small operations, so a solve on the
default single CPU device uses one core however many the machine has. With several CPU devices the
robots shard over them (``mmpgo_jax.sharding.Sharded``) and each core runs its
own robots: on a 2-core Intel Xeon (benchmarks/thread_threshold.md) two devices ran 0.57-0.90x the
time per iteration of one from 50 to 1045 poses, their program taking 0.1-1.4 s longer to compile
cold; on a 2-core AMD EPYC MIT (808 poses) ran at the same speed on 1 and 2
(benchmarks/profile_step.md, older code) and intel (1728 poses) 1.7x faster on 2.
JAX fixes its CPU device count when its backend starts, so the library never changes it on import:
a program asks for the cores with :func:`use_cpu_cores` before its first JAX computation (the
``mmpgo`` command does so when it starts), and :func:`auto_layout` — ``solve``'s default layout — then uses them.
"""

from __future__ import annotations

import os

__all__ = ["AUTO_THREAD_POSES", "auto_layout", "cpu_cores", "use_cpu_cores"]

# A solve splits its robots over the CPU devices from this many poses on. Below it a run's 1000
# iterations take about 0.2 s either way, and the exchange between devices, a fixed cost per
# iteration, weighs most: on the AMD EPYC it ate the second core's gain at 808 poses (MIT), on the
# Intel Xeon two devices still won at 50 (benchmarks/thread_threshold.md).
AUTO_THREAD_POSES = 200


def cpu_cores() -> int:
    """The cores this process may run on."""
    try:
        return len(os.sched_getaffinity(0))
    except AttributeError:  # not on Linux
        return os.cpu_count() or 1


def use_cpu_cores(n: int | None = None) -> int:
    """Give JAX's CPU backend ``n`` devices (default: one per core this process may use), so that
    ``solve`` splits the robots of graphs of ``AUTO_THREAD_POSES`` poses or more over them. Call it
    before the first JAX computation (right after the imports); returns the device count set.
    RuntimeError (one line) when JAX has already started its backends."""
    import jax

    n = cpu_cores() if n is None else int(n)
    if n < 1:
        raise ValueError(f"use_cpu_cores: n must be >= 1, got {n}")
    try:
        jax.config.update("jax_num_cpu_devices", n)
    except RuntimeError:
        raise RuntimeError("use_cpu_cores() must run before the first JAX computation of the process "
                           "(JAX fixes its CPU devices when its backend starts): call it right after the "
                           "imports") from None
    return n


def auto_layout(num_poses: int, num_robots: int, threads: int | None = None):
    """``solve``'s default layout: on a CPU backend with several CPU devices (:func:`use_cpu_cores`)
    and a graph of ``AUTO_THREAD_POSES`` poses or more, the robots sharded over min(devices, robots)
    of them; otherwise one device. ``threads``: the devices to use at most (1: one device)."""
    import jax

    from .._mm.layouts import OneDevice

    if jax.default_backend() != "cpu" or (threads is None and num_poses < AUTO_THREAD_POSES):
        return OneDevice()
    devices = jax.devices("cpu")
    n = min(len(devices), num_robots, threads or len(devices))
    if n < 2:
        return OneDevice()
    from .._distributed.layout import Sharded  # the sharded machinery loads only when it runs

    return Sharded(devices=devices[:n])
