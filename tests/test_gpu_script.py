"""benchmarks/gpu.py, the run prepared for a GPU machine, works without one: its --quick version on
a CPU runs every part in its own process and writes a report with every section and no failure
(a session lent a GPU has minutes to run it; a broken script would waste them)."""

import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]


@pytest.mark.slow
def test_gpu_script_quick_on_a_cpu(tmp_path, benchmark_file):
    benchmark_file("MIT.g2o")  # skips without the benchmark files
    out = tmp_path / "gpu_quick.md"
    proc = subprocess.run([sys.executable, str(ROOT / "benchmarks" / "gpu.py"), "--quick", "--out", str(out)],
                          capture_output=True, text=True, timeout=600)
    assert proc.returncode == 0, proc.stdout[-2000:] + proc.stderr[-2000:]
    text = out.read_text()
    assert "This ran on a CPU" in text
    for section in ("(a) Benchmark files", "(b) Sweep", "(c) Large Cube graphs", "(d) Other paths"):
        assert section in text, section
    unfinished = text.split("## Skipped, failed or cut short", 1)[1]
    assert "Nothing." in unfinished, unfinished
    rows = [line for line in text.splitlines() if line.startswith("| ") and "ms / iteration" not in line]
    assert any(line.startswith("| MITb |") for line in rows)
    assert any(line.startswith("| tls-distributed MITb |") for line in rows)
