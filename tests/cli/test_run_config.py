"""``run --config`` / ``--set``: every key reachable, runs reproducible from their own config, clear errors."""

from __future__ import annotations

import json

import pytest
import yaml
from click.testing import CliRunner

from trianflow_vo.cli.main import main
from trianflow_vo.config import Config, load_config


def _run(*args):
    return CliRunner().invoke(main, ["run", *map(str, args)], catch_exceptions=False)


@pytest.fixture(scope="module")
def first_run(tmp_path_factory, request):
    from conftest import SAMPLE

    if not SAMPLE.is_dir():
        pytest.skip(f"sample not found at {SAMPLE}")
    out = tmp_path_factory.mktemp("cfg") / "a"
    r = _run(SAMPLE, "--end", 24, "--stride", 3, "--set", "sampling.n_samples=3000", "--seed", 2, "--out", out,
             "--quiet", "--no-plot")
    assert r.exit_code == 0, r.output
    return SAMPLE, out


def test_effective_config_is_written_to_run_json_and_config_yaml(first_run):
    _, out = first_run
    doc = json.loads((out / "run.json").read_text())
    cfg = load_config(out / "config.yaml")
    assert cfg.to_dict() == doc["config"]
    assert cfg.input.stride == 3 and cfg.input.end == 24 and cfg.sampling.n_samples == 3000
    assert cfg.sampling.seed == 2 and cfg.output.plot is False
    assert load_config(out / "run.json") == cfg
    assert (out / "config.yaml").read_text().startswith("#")


@pytest.mark.parametrize("name", ["config.yaml", "run.json"])
def test_config_file_reproduces_the_run_byte_for_byte(first_run, tmp_path, name):
    seq, out = first_run
    r = _run(seq, "--config", out / name, "--out", tmp_path / "b", "--quiet")
    assert r.exit_code == 0, r.output
    assert (tmp_path / "b" / "poses.txt").read_bytes() == (out / "poses.txt").read_bytes()
    assert (tmp_path / "b" / "frames.txt").read_bytes() == (out / "frames.txt").read_bytes()


def test_a_changed_key_changes_the_run(first_run, tmp_path):
    seq, out = first_run
    r = _run(seq, "--config", out / "config.yaml", "--set", "sampling.seed=5", "--out", tmp_path / "c", "--quiet")
    assert r.exit_code == 0, r.output
    assert (tmp_path / "c" / "poses.txt").read_bytes() != (out / "poses.txt").read_bytes()
    assert load_config(tmp_path / "c" / "config.yaml").sampling.seed == 5


def test_precedence_config_then_set_then_flags(tmp_path, sample_seq):
    cfg = tmp_path / "my.yaml"
    cfg.write_text(yaml.safe_dump({"input": {"stride": 4, "end": 20}, "sampling": {"seed": 1},
                                   "keyframes": {"min_parallax_px": 2.5}}))
    r = _run(sample_seq, "--config", cfg, "--set", "input.stride=5", "--set", "sampling.seed=3", "--seed", 4,
             "--out", tmp_path / "o", "--quiet", "--no-plot")
    assert r.exit_code == 0, r.output
    got = load_config(tmp_path / "o" / "config.yaml")
    assert (got.input.stride, got.input.end, got.sampling.seed, got.keyframes.min_parallax_px) == (5, 20, 4, 2.5)
    assert [int(x) for x in (tmp_path / "o" / "frames.txt").read_text().split()] == [0, 5, 10, 15]


def test_preset_by_name(tmp_path, sample_seq):
    r = _run(sample_seq, "--config", "indoor", "--end", 7, "--stride", 3, "--out", tmp_path / "o", "--quiet",
             "--no-plot")
    assert r.exit_code == 0, r.output
    assert json.loads((tmp_path / "o" / "run.json").read_text())["flow_source"]["preset"] == "fine"


@pytest.mark.parametrize("args, words", [
    (["--set", "flow.dis_preset=ultra"], ["flow.dis_preset", "fast", "medium", "fine"]),
    (["--set", "flow.foo=1"], ["flow.foo", "dis_preset", "model"]),
    (["--set", "flwo.model=x"], ["flwo", "valid sections"]),
    (["--set", "sampling.top_ratio=2"], ["sampling.top_ratio", "(0, 1]"]),
    (["--set", "sampling.n_samples"], ["sampling.n_samples"]),
    (["--config", "no-such-preset"], ["no-such-preset"]),
])
def test_bad_config_is_one_line_exit_2(tmp_path, sample_seq, args, words):
    r = CliRunner().invoke(main, ["run", str(sample_seq), "--out", str(tmp_path / "o"), *args])
    assert r.exit_code == 2, r.output
    lines = r.output.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("Error: "), r.output
    for w in words:
        assert w in lines[0], (w, lines[0])
    assert "Traceback" not in r.output and not (tmp_path / "o").exists()


def test_every_config_key_is_reachable_with_set():
    from trianflow_vo.config import apply_overrides, config_keys

    base = Config()
    for key, _type, default, _help in config_keys():
        section, field = key.split(".")
        assert getattr(getattr(base, section), field) == default, key
        # setting a key to its own default through --set is accepted and changes nothing
        value = json.dumps(list(default) if isinstance(default, tuple) else (str(default) if hasattr(default, "parts")
                                                                              else default))
        assert apply_overrides(base, [f"{key}={value}"]) == base, key
