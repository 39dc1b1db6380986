"""``benchmarks/bench_robustness.py``: the CPU a table was measured on, the compare's warning, and its paired test."""

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


def test_sign_flip_p_known_answers(br):
    # all of n seeds worse: only the all-plus and all-minus flips are as extreme, p = 2 / 2^n
    assert br.paired_sign_flip_p([0.1, 0.2, 0.3]) == pytest.approx(2 / 8)
    assert br.paired_sign_flip_p([0.1] * 12) == pytest.approx(2 / 4096)
    # symmetric differences: every flip is as extreme as a mean of zero
    assert br.paired_sign_flip_p([0.1, -0.1]) == 1.0
    # one outlying seed against eleven slightly better ones: every flip is as far from zero, no evidence
    assert br.paired_sign_flip_p([2.0] + [-0.01] * 11) == 1.0
    assert br.paired_sign_flip_p([0.3]) is None
    # more than 16 seeds: random flips, still small for a consistent change
    assert br.paired_sign_flip_p([0.1] * 20) < 1e-3


def _seeded(path: Path, ates: list[float]) -> str:
    runs = [{"seed": s, "status": "completed", "ate_pct": a} for s, a in enumerate(ates)]
    med = sorted(ates)[len(ates) // 2]
    summary = {"ate_pct": med, "ate_pct_max": max(ates), "fps": 10.0, "n_completed": len(ates)}
    path.write_text(json.dumps({"label": path.stem, "meta": {"args": ""},
                                "cases": {"clip/s1": {"summary": summary, "runs": runs}}}))
    return str(path)


def test_compare_flags_a_change_every_seed_shows_though_under_the_tolerance(br, tmp_path):
    a = [1.0, 1.2, 0.9, 1.1, 1.0, 1.3, 0.8, 1.0, 1.1, 0.9, 1.2, 1.0]
    worse = _seeded(tmp_path / "w.json", [x * 1.08 for x in a])  # 8 % worse on every seed: under 1.10
    text, n = br.compare(_seeded(tmp_path / "a.json", a), worse, 1.1, 0.02)
    assert n == 1 and "worse paired" in text and "0/12, 1.08, p 0.000488" in text
    # the same shift on three seeds cannot be told from noise
    text3, n3 = br.compare(_seeded(tmp_path / "a3.json", a[:3]), _seeded(tmp_path / "w3.json", [x * 1.08 for x in a[:3]]),
                           1.1, 0.02)
    assert n3 == 0 and "0/3, 1.08, p 0.25" in text3
    # better on every seed is not worse
    assert br.compare(_seeded(tmp_path / "a2.json", a), _seeded(tmp_path / "b.json", [x / 1.08 for x in a]),
                      1.1, 0.02)[1] == 0
