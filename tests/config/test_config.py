"""The configuration tree: defaults, validation, files, presets, overrides and round trips."""

from __future__ import annotations

import dataclasses
import json
import math
import random
from pathlib import Path

import pytest
import yaml

from trianflow_vo.config import (
    BackendConfig, Config, ConfigError, DepthConfig, FlowConfig, GeometryConfig, InputConfig, KeyframeConfig,
    OutputConfig, RuntimeConfig, SamplingConfig, ScaleConfig, apply_overrides, config_from_dict, config_keys,
    load_config, merge_dict, preset_names, write_config_yaml,
)
from trianflow_vo.errors import VOError

REPO = Path(__file__).resolve().parents[2]

DEFAULTS = {
    "input": {"start": 0, "end": None, "stride": 1, "size": None, "intrinsics": None, "calib": None,
              "readout": 0.0},
    "flow": {"model": None, "dis_preset": "medium", "ahead": True},
    "depth": {"model": None, "fusion": True, "decay": 0.8, "max_log_gap": 0.3},
    "sampling": {"n_samples": 12000, "top_ratio": 0.2, "max_anchors": 6000, "seed": 0},
    "geometry": {"ransac_method": "ransac", "ransac_threshold_px": 0.25, "ransac_subset": 1000, "refine": True,
                 "epi_inlier_px": 0.5, "min_inliers": 100, "min_angle_rad": 1e-3, "min_valid_fraction": 0.1, "epipolar_correction": False,
                 "min_local_angle_rad": 0.0, "local_angle_keep": 0.75, "local_angle_cell_px": 32.0, "pnp_reproj_px": 1.0,
                 "pnp_min_inlier_ratio": 0.1},
    "scale": {"source": "auto", "min_points": 20, "depth_min_flow_px": 5.0, "depth_fit_threshold": 1.0,
              "depth_fit_trials": 100, "depth_fit_min_points": 100, "depth_max": 50.0, "pnp_check_ratio": 1.5,
              "pnp_check_ratio_low": 1.15, "pnp_check_low_parallax_px": 8.0},
    "keyframes": {"static_flow_px": 0.25, "policy": "gric", "min_parallax_px": 3.0, "max_direction_deg": 0.5, "init_min_parallax_px": 1.0,
                  "depth_min_parallax_deg": 0.2, "min_inlier_share": 0.5, "handon_min_angle_deg": 3.0,
                  "max_flow_fraction": 0.1, "max_next_flow_fraction": 0.125, "noise_floor_px": 0.1, "independent_matches": 500},
    "backend": {"kind": "window-ba", "window": 6, "fixed": 2,
                "huber_px": 1.0, "max_iterations": 5, "every": 2, "max_tracks": 250, "cell_px": 32, "track_texture_px": 9,
                "track_fb_px": 1.0, "track_epi_px": 1.0, "outlier_px": 3.0, "min_points": 30, "step_factors": True,
                "step_rot_deg": 0.05, "step_trans": 0.02, "step_trans_pnp": 1.0, "depth_correction": "shape",
                "depth_correction_max": 1.5, "depth_correction_t": 4.24, "depth_correction_min": 0.1,
                "concurrent": True, "max_shift": 0.5, "max_rotation_deg": 3.0,
                "anchors": 2, "anchor_keep": 48, "anchor_revisit_ratio": 1.0, "anchor_max_angle_deg": 30.0,
                "anchor_min_links": 40, "anchor_max_parallax_px": 100.0, "anchor_max_zoom": 1.25,
                "anchor_max_shared": 40, "anchor_gate_px": 20.0},
    "output": {"gt": None, "plot": True, "rerun": None, "rerun_spawn": False},
    "runtime": {"threads": 2, "blas_threads": 1},
}


def custom() -> Config:
    """A config with every kind of non-default value (paths, tuples, awkward floats)."""
    return Config(
        input=InputConfig(start=3, end=90, stride=2, size=(256, 832), intrinsics=(718.856, 718.856, 607.1928, 185.2157),
                          calib=Path("data/calib.txt")),
        flow=FlowConfig(model=Path("/models/pwc flow.onnx"), dis_preset="fine"),
        depth=DepthConfig(model=Path("depth.onnx"), fusion=False, decay=0.1 + 0.2, max_log_gap=1e-7),
        sampling=SamplingConfig(n_samples=100000, top_ratio=1.0, max_anchors=0, seed=12345),
        geometry=GeometryConfig(ransac_method="magsac", ransac_threshold_px=2 / 3, ransac_subset=8, refine=False,
                                epi_inlier_px=123456.789e3, min_inliers=8, min_angle_rad=0.0, pnp_reproj_px=1e-300),
        scale=ScaleConfig(min_points=3, pnp_check_ratio=0.0),
        keyframes=KeyframeConfig(static_flow_px=0.0, min_parallax_px=100.0),
        backend=BackendConfig(kind="none"),
        output=OutputConfig(gt=Path("gt/00.txt"), plot=False, rerun=Path("out/run.rrd"), rerun_spawn=True),
        runtime=RuntimeConfig(threads=64),
    )


def err(fn, *args) -> str:
    with pytest.raises(ConfigError) as e:
        fn(*args)
    msg = str(e.value)
    assert "\n" not in msg, msg
    return msg


# -- defaults and the tree ------------------------------------------------------------------------------------
def test_defaults():
    c = Config()
    assert c.to_dict() == DEFAULTS
    assert list(c.to_dict()) == list(DEFAULTS)  # section order
    assert c.geometry.min_angle_rad == 1e-3 and c.flow.dis_preset == "medium" and c.input.size is None


def test_frozen_and_hashable():
    c = Config()
    with pytest.raises(dataclasses.FrozenInstanceError):
        c.sampling.seed = 3  # type: ignore[misc]
    assert hash(custom()) == hash(custom())


def test_config_keys_cover_every_field():
    keys = config_keys()
    assert [k for k, *_ in keys] == [f"{s}.{k}" for s, sec in DEFAULTS.items() for k in sec]
    for key, typ, default, help in keys:
        s, k = key.split(".")
        assert default == DEFAULTS[s][k] and (default is None) == (DEFAULTS[s][k] is None)
        assert typ and help and "\n" not in help, key
    types = dict((k, t) for k, t, _, _ in keys)
    assert types["sampling.top_ratio"] == "float in (0, 1]"
    assert types["flow.dis_preset"] == "one of fast, medium, fine"
    assert types["flow.model"] == "path or null"


def test_error_is_vo_error_and_value_error():
    assert issubclass(ConfigError, VOError) and issubclass(ConfigError, ValueError)


# -- round trips -------------------------------------------------------------------------------------------------
def test_dict_round_trip():
    for c in (Config(), custom()):
        d = c.to_dict()
        assert config_from_dict(d) == c
        assert json.loads(json.dumps(d)) == d  # plain JSON types only
    d = custom().to_dict()
    assert d["input"]["size"] == [256, 832] and d["flow"]["model"] == "/models/pwc flow.onnx"


def test_yaml_round_trip(tmp_path):
    p = tmp_path / "config.yaml"
    for c in (Config(), custom()):
        write_config_yaml(c, p)
        first = p.read_text().splitlines()[0]
        assert first.startswith("#") and "trianflow-vo run SEQ --config" in first
        back = load_config(p)
        assert back == c
        assert math.copysign(1.0, back.geometry.min_angle_rad) == 1.0


def test_yaml_floats_bit_identical(tmp_path):
    rng = random.Random(7)
    p = tmp_path / "f.yaml"
    values = [rng.uniform(1e-9, 1.0) for _ in range(200)] + [rng.lognormvariate(0, 20) for _ in range(200)]
    values += [5e-324, 1e-5, 1e16, 1.7976931348623157e308, 0.1 + 0.2]
    for v in values:
        c = Config(geometry=GeometryConfig(ransac_threshold_px=v))
        write_config_yaml(c, p)
        assert load_config(p).geometry.ransac_threshold_px.hex() == v.hex()


def test_json_run_json_and_plain(tmp_path):
    c = custom()
    run = tmp_path / "run.json"
    run.write_text(json.dumps({"version": "0.1.0", "counts": {"TWO_VIEW": 3}, "config": c.to_dict()}))
    assert load_config(run) == c
    plain = tmp_path / "plain.json"
    plain.write_text(json.dumps({"sampling": {"seed": 9}}))
    assert load_config(plain) == Config(sampling=SamplingConfig(seed=9))


def test_partial_file_and_merge(tmp_path):
    p = tmp_path / "part.yml"
    p.write_text("sampling:\n  n_samples: 8000\nflow:\n  dis_preset: fast\ndepth:\n")
    c = load_config(p)
    assert c == Config(sampling=SamplingConfig(n_samples=8000), flow=FlowConfig(dis_preset="fast"))
    c2 = merge_dict(c, {"sampling": {"seed": 4}}, "flags")
    assert c2.sampling == SamplingConfig(n_samples=8000, seed=4) and c2.flow.dis_preset == "fast"
    empty = tmp_path / "empty.yaml"
    empty.write_text("# nothing set\n")
    assert load_config(empty) == Config()


# -- errors ------------------------------------------------------------------------------------------------------
def test_unknown_section_and_key():
    m = err(config_from_dict, {"flwo": {"dis_preset": "fine"}}, "cfg.yaml")
    assert m == ("cfg.yaml: unknown section 'flwo'; valid sections: input, flow, depth, sampling, geometry, "
                 "scale, keyframes, backend, output, runtime")
    m = err(config_from_dict, {"flow": {"foo": 1}}, "cfg.yaml")
    assert m == "cfg.yaml: unknown key 'flow.foo'; valid keys of flow: ahead, dis_preset, model"


def test_choice_range_and_type_errors():
    cases = [
        ({"flow": {"dis_preset": "ultra"}}, "cfg.yaml: flow.dis_preset: 'ultra' is not one of fast, medium, fine"),
        ({"geometry": {"ransac_method": "lmeds"}}, "geometry.ransac_method: 'lmeds' is not one of ransac, magsac, 8point"),
        ({"backend": {"kind": "ba"}}, "backend.kind: 'ba' is not one of window-ba, none"),
        ({"sampling": {"top_ratio": 2.0}}, "cfg.yaml: sampling.top_ratio: 2.0 is out of range (0, 1]"),
        ({"sampling": {"top_ratio": 0}}, "sampling.top_ratio: 0 is out of range (0, 1]"),
        ({"sampling": {"n_samples": 99}}, "sampling.n_samples: 99 is out of range [100, 100000]"),
        ({"runtime": {"threads": 65}}, "runtime.threads: 65 is out of range [1, 64]"),
        ({"runtime": {"blas_threads": 0}}, "runtime.blas_threads: 0 is out of range [1, 64]"),
        ({"input": {"stride": 0}}, "input.stride: 0 is out of range; must be >= 1"),
        ({"input": {"readout": -1.5}}, "input.readout: -1.5 is out of range [-1, 1]"),
        ({"backend": {"anchor_revisit_ratio": 1.5}}, "backend.anchor_revisit_ratio: 1.5 is out of range (0, 1]"),
        ({"backend": {"anchors": 11}}, "backend.anchors: 11 is out of range [0, 10]"),
        ({"backend": {"anchor_max_zoom": 0.8}}, "backend.anchor_max_zoom: 0.8 is out of range; must be >= 1"),
        ({"depth": {"max_log_gap": 0.0}}, "depth.max_log_gap: 0.0 is out of range; must be > 0"),
        ({"scale": {"pnp_check_ratio": 0.5}}, "scale.pnp_check_ratio: 0.5 is out of range; must be 0 (off) or > 1"),
        ({"input": {"start": 2.5}}, "cfg.yaml: input.start: 2.5 is not an integer"),
        ({"sampling": {"seed": 3.0}}, "sampling.seed: 3.0 is not an integer"),
        ({"sampling": {"seed": True}}, "sampling.seed: true is not an integer"),
        ({"output": {"plot": "yes"}}, "output.plot: 'yes' is not a bool"),
        ({"output": {"plot": 1}}, "output.plot: 1 is not a bool"),
        ({"depth": {"decay": "0.5"}}, "depth.decay: '0.5' is not a number"),
        ({"depth": {"decay": float("nan")}}, "depth.decay: nan is not a finite number"),
        ({"flow": {"model": 3}}, "flow.model: 3 is not a path"),
        ({"flow": {"dis_preset": None}}, "flow.dis_preset: null is not allowed"),
        ({"input": {"size": [250, 832]}}, "input.size: [250, 832] is not two positive multiples of 64"),
        ({"input": {"size": "256x"}}, "input.size: '256x' is not HxW or [h, w]"),
        ({"input": {"size": [256, 832, 3]}}, "input.size: [256, 832, 3] is not HxW or [h, w]"),
        ({"input": {"intrinsics": [0, 700, 300, 200]}}, "input.intrinsics: [0.0, 700.0, 300.0, 200.0] has fx or fy <= 0"),
        ({"input": {"intrinsics": "700,700,300"}}, "input.intrinsics: '700,700,300' is not fx,fy,cx,cy"),
        ({"input": {"start": 10, "end": 10}}, "cfg.yaml: input.end: 10 must be greater than input.start (10)"),
        ({"flow": ["fine"]}, "cfg.yaml: section 'flow' must be a mapping of keys, got a list"),
    ]
    for data, expected in cases:
        m = err(config_from_dict, data, "cfg.yaml")
        assert m.startswith("cfg.yaml: ") and expected in m, (m, expected)


def test_floats_accept_ints_and_exponent_strings():
    c = config_from_dict({"depth": {"decay": 1}, "geometry": {"min_angle_rad": "1e-4"}})
    assert c.depth.decay == 1.0 and type(c.depth.decay) is float
    assert c.geometry.min_angle_rad == 1e-4


def test_file_errors(tmp_path):
    bad = tmp_path / "bad.yaml"
    bad.write_text("flow:\n  dis_preset: fine\n  model: [a\nsampling:\n  seed: 1\n")
    m = err(load_config, bad)
    assert m.startswith(f"{bad}:") and "invalid YAML" in m
    line = int(m[len(str(bad)) + 1:].split(":")[0])
    assert 3 <= line <= 5
    badj = tmp_path / "bad.json"
    badj.write_text('{"sampling": {\n  "seed": 1,\n}}')
    m = err(load_config, badj)
    assert m.startswith(f"{badj}:3: invalid JSON"), m
    lst = tmp_path / "list.yaml"
    lst.write_text("- a\n- b\n")
    m = err(load_config, lst)
    assert m.startswith(f"{lst}: the document must be a mapping of sections"), m
    m = err(load_config, tmp_path / "missing.yaml")
    assert m == f"{tmp_path / 'missing.yaml'}: no such file"
    m = err(load_config, "kiti")
    assert m == "kiti: no such file or preset; presets: default, indoor, kitti"
    val = tmp_path / "val.yaml"
    val.write_text("sampling:\n  top_ratio: 2.0\n")
    assert err(load_config, val) == f"{val}: sampling.top_ratio: 2.0 is out of range (0, 1]"
    rj = tmp_path / "run.json"
    rj.write_text(json.dumps({"config": [1]}))
    assert "'config' must be a mapping" in err(load_config, rj)


def test_post_init_validates():
    with pytest.raises(ValueError) as e:
        SamplingConfig(top_ratio=2.0)
    assert isinstance(e.value, ConfigError)
    assert str(e.value) == "SamplingConfig: sampling.top_ratio: 2.0 is out of range (0, 1]"
    with pytest.raises(ConfigError, match="flow.dis_preset: 'ultra' is not one of fast, medium, fine"):
        FlowConfig(dis_preset="ultra")  # type: ignore[arg-type]
    with pytest.raises(ConfigError, match="input.end"):
        InputConfig(start=5, end=5)
    with pytest.raises(ConfigError, match="input.start: 1.5 is not an integer"):
        InputConfig(start=1.5)  # type: ignore[arg-type]
    with pytest.raises(ConfigError, match="section 'flow' must be a FlowConfig"):
        Config(flow={"dis_preset": "fine"})  # type: ignore[arg-type]
    with pytest.raises(ConfigError):
        dataclasses.replace(Config().geometry, min_inliers=7)


def test_post_init_normalises():
    i = InputConfig(size=[256, 832], intrinsics=[700, 700, 300, 200], calib="c.txt")  # type: ignore[arg-type]
    assert i.size == (256, 832) and i.intrinsics == (700.0, 700.0, 300.0, 200.0) and i.calib == Path("c.txt")
    assert all(type(v) is float for v in i.intrinsics)
    assert i == InputConfig(size=(256, 832), intrinsics=(700.0, 700.0, 300.0, 200.0), calib=Path("c.txt"))


# -- overrides ---------------------------------------------------------------------------------------------------
def test_overrides_of_each_type():
    c = apply_overrides(Config(), [
        "sampling.seed=3",                     # int
        "depth.decay=0.5",                     # float
        "keyframes.min_parallax_px=4",         # int into a float
        "geometry.refine=false",               # bool
        "output.plot = false",                 # spaces around '='
        "input.end=50",
        "input.end=null",                      # null (the later item wins)
        "input.size=[256, 832]",               # list
        "input.intrinsics=718.8,718.8,607.1,185.2",
        "flow.dis_preset=fine",                # Literal
        "flow.model=models/flow.onnx",         # path
        "geometry.min_angle_rad=1e-4",
    ])
    assert c.sampling.seed == 3 and c.depth.decay == 0.5
    assert c.keyframes.min_parallax_px == 4.0 and type(c.keyframes.min_parallax_px) is float
    assert c.geometry.refine is False and c.output.plot is False
    assert c.input.end is None and c.input.size == (256, 832)
    assert c.input.intrinsics == (718.8, 718.8, 607.1, 185.2)
    assert c.flow.dis_preset == "fine" and c.flow.model == Path("models/flow.onnx")
    assert c.geometry.min_angle_rad == 1e-4
    assert apply_overrides(Config(), ["input.size=256x832"]).input.size == (256, 832)
    assert apply_overrides(Config(), ["input.size=512X1024"]).input.size == (512, 1024)
    untouched = dict(DEFAULTS, sampling=dict(DEFAULTS["sampling"], seed=3))
    assert apply_overrides(Config(), ["sampling.seed=3"]).to_dict() == untouched


def test_override_errors():
    c = Config()
    assert err(apply_overrides, c, ["flow.dis_preset=ultra"]) == \
        "--set flow.dis_preset: 'ultra' is not one of fast, medium, fine"
    assert err(apply_overrides, c, ["sampling.top_ratio=2.0"]) == "--set sampling.top_ratio: 2.0 is out of range (0, 1]"
    assert err(apply_overrides, c, ["sampling.seed=2.5"]) == "--set sampling.seed: 2.5 is not an integer"
    assert err(apply_overrides, c, ["output.plot=yes please"]).startswith("--set output.plot: 'yes please' is not a bool")
    assert err(apply_overrides, c, ["flow.foo=1"]) == "--set: unknown key 'flow.foo'; valid keys of flow: ahead, dis_preset, model"
    assert err(apply_overrides, c, ["flwo.dis_preset=fine"]).startswith("--set: unknown section 'flwo'; valid sections: input,")
    m = err(apply_overrides, c, ["sampling.seed"])
    assert m.startswith("--set: 'sampling.seed' is not section.key=value")
    m = err(apply_overrides, c, ["seed=3"])
    assert m.startswith("--set: 'seed=3' is not section.key=value")
    m = err(apply_overrides, c, ["flow.model=[a"])
    assert m.startswith("--set flow.model: cannot read value '[a' as YAML")
    assert err(apply_overrides, c, ["sampling.seed=-1"], "--flag").startswith("--flag sampling.seed: -1 is out of range")


# -- presets -----------------------------------------------------------------------------------------------------
def test_presets():
    assert preset_names() == ["default", "indoor", "kitti"]
    assert load_config("default") == Config()
    assert load_config("kitti") == Config()
    indoor = load_config("indoor").to_dict()
    diff = {(s, k) for s in DEFAULTS for k in DEFAULTS[s] if indoor[s][k] != DEFAULTS[s][k]}
    assert diff == {("flow", "dis_preset")} and indoor["flow"]["dis_preset"] == "fine"


def test_default_yaml_lists_every_key():
    doc = yaml.safe_load((REPO / "configs" / "default.yaml").read_text())
    assert doc == DEFAULTS  # every key present, with its default, no extra
    text = (REPO / "configs" / "default.yaml").read_text()
    for key, *_ in config_keys():
        line = next(ln for ln in text.splitlines() if ln.strip().startswith(key.split(".")[1] + ":"))
        assert "#" in line, f"no comment for {key}"


def test_existing_file_wins_over_preset_and_dir_does_not(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    (tmp_path / "kitti").mkdir()  # a sequence folder named like a preset: still the preset
    assert load_config("kitti") == Config()
    (tmp_path / "indoor").write_text("sampling:\n  seed: 5\n")
    assert load_config("indoor") == Config(sampling=SamplingConfig(seed=5))


def test_readme_table_is_current():
    from trianflow_vo.config import _keys_markdown

    text = (REPO / "configs" / "README.md").read_text()
    assert _keys_markdown() in text
    for word in ("--config", "--set section.key=value", "defaults < `--config` < `--set`", "indoor", "kitti"):
        assert word in text
