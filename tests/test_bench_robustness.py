"""``benchmarks/bench_robustness.py``: the CPU a table was measured on, and the compare's warning."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

EPYC = "processor\t: 0\nmodel name\t: AMD EPYC\nflags\t\t: fpu sse2 avx fma avx2\n\nprocessor\t: 1\n" \
       "model name\t: AMD EPYC\nflags\t\t: fpu sse2 avx fma avx2\n"
XEON = "processor\t: 0\nmodel name\t: Intel(R) Xeon(R) CPU @ 2.20GHz\nflags\t\t: avx fma avx2 avx512f avx512bw\n"


@pytest.fixture(scope="module")
def br(benchmark_module):
    return benchmark_module("bench_robustness")


def test_cpu_names_the_model_and_the_extensions_it_lacks(br):
    assert br.cpu_description(EPYC) == "AMD EPYC (avx2, fma; no avx512f)"
    assert br.cpu_description(XEON) == "Intel(R) Xeon(R) CPU @ 2.20GHz (avx512f, avx2, fma)"
    assert br.cpu_description("model name\t: Old\nflags\t: fpu sse2\n") == "Old (none of avx512f, avx2, fma)"
    assert br.cpu_description("model name\t: No flags line\n") == "No flags line"


def _table(path: Path, cpu: str | None, ate: float) -> str:
    meta = {"args": ""} | ({"cpu": cpu} if cpu else {})
    summary = {"ate_pct": ate, "ate_pct_max": ate, "fps": 10.0, "n_completed": 3}
    path.write_text(json.dumps({"label": path.stem, "meta": meta, "cases": {"clip/s1": {"summary": summary}}}))
    return str(path)


def test_compare_warns_when_the_tables_come_from_different_cpus(br, tmp_path):
    a = _table(tmp_path / "a.json", br.cpu_description(EPYC), 1.0)
    b = _table(tmp_path / "b.json", br.cpu_description(XEON), 1.0)
    text, worse = br.compare(a, b, 1.1, 0.02)
    assert "different CPUs" in text and "AMD EPYC" in text and "Xeon" in text
    assert worse == 0


def test_compare_on_one_cpu_or_unrecorded_cpus_does_not_warn(br, tmp_path):
    a = _table(tmp_path / "a.json", br.cpu_description(EPYC), 1.0)
    b = _table(tmp_path / "b.json", br.cpu_description(EPYC), 1.5)
    text, worse = br.compare(a, b, 1.1, 0.02)
    assert "different CPUs" not in text and worse == 1
    old_a, old_b = _table(tmp_path / "c.json", None, 1.0), _table(tmp_path / "d.json", None, 1.0)
    assert "different CPUs" not in br.compare(old_a, old_b, 1.1, 0.02)[0]
    assert "not recorded" in br.compare(old_a, b, 1.1, 0.02)[0]
