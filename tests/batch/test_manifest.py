"""Manifest reading, sweep expansion and each job's configuration (pure: no Ray, no sequence opened).

Known answers first (fields read, paths resolved against the manifest, the cartesian product
and its folders, the order of overrides, a job's config equal to that of the equivalent ``run``
command line), then every kind of bad input with the file, line or key it names.
"""

from __future__ import annotations

from pathlib import Path

import pytest
import yaml

from trianflow_vo.batch.jobs import job_config
from trianflow_vo.batch.manifest import (
    Job,
    expand_jobs,
    parse_sweeps,
    read_manifest,
    sequences_from_args,
    split_values,
    sweep_combinations,
    sweep_folder,
)
from trianflow_vo.cli.config_flags import build_config
from trianflow_vo.errors import ConfigError, InputError


def _write(path: Path, text: str) -> Path:
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(text)
    return path


# -- YAML / CSV: known answers ----------------------------------------------------------------------------------
def test_yaml_manifest_fields_and_relative_paths(tmp_path):
    m = _write(tmp_path / "lists" / "seqs.yaml", """
sequences:
  - path: ../data/k06
    name: k06
    gt: ../data/k06/poses.txt
    stride: 2
    end: 40
    lengths: [20, 10, 10]
    set:
      sampling.n_samples: 3000
      flow.dis_preset: fine
      input.size: [128, 384]
  - /abs/seq00
  - path: rel00
    intrinsics: [700, 700, 600, 180]
""")
    s1, s2, s3 = read_manifest(m)
    data = (tmp_path / "data").absolute()
    assert s1.path == str(data / "k06") and s1.name == "k06"
    assert dict(s1.fields) == {"gt": str(data / "k06" / "poses.txt"), "stride": 2, "end": 40}
    assert s1.lengths == (10.0, 20.0)  # sorted, duplicates dropped
    assert s1.overrides == ('sampling.n_samples=3000', 'flow.dis_preset="fine"', "input.size=[128, 384]")
    assert s1.origin == f"{m}: sequence 1"
    assert (s2.path, s2.name, s2.fields, s2.overrides, s2.lengths) == ("/abs/seq00", "seq00", (), (), None)
    assert s3.path == str((tmp_path / "lists" / "rel00").absolute()) and s3.name == "rel00"
    assert dict(s3.fields) == {"intrinsics": (700.0, 700.0, 600.0, 180.0)}


def test_yaml_manifest_may_be_a_bare_list(tmp_path):
    m = _write(tmp_path / "s.yml", "- a\n- path: b\n  name: bee\n")
    assert [(s.name, Path(s.path).name) for s in read_manifest(m)] == [("a", "a"), ("bee", "b")]


def test_csv_manifest(tmp_path):
    m = _write(tmp_path / "s.csv", """# a comment line
name,path,gt,stride,intrinsics,set,lengths
k06,data/k06,data/k06/poses.txt,3,,sampling.seed=4;keyframes.min_parallax_px=2.5,"10,20"

,data/k00,,,"700,700,600,180",,
""")
    a, b = read_manifest(m)
    assert a.name == "k06" and a.path == str((tmp_path / "data" / "k06").absolute())
    assert dict(a.fields) == {"gt": str((tmp_path / "data" / "k06" / "poses.txt").absolute()), "stride": 3}
    assert a.overrides == ("sampling.seed=4", "keyframes.min_parallax_px=2.5") and a.lengths == (10.0, 20.0)
    assert a.origin == f"{m}:3"
    assert b.name == "k00" and dict(b.fields) == {"intrinsics": (700.0, 700.0, 600.0, 180.0)}
    assert b.origin == f"{m}:5"  # the blank line is not a row, but lines keep their numbers


def test_sequences_from_args_resolve_against_cwd(tmp_path):
    (s,) = sequences_from_args(["x/seq1"], cwd=tmp_path)
    assert s.path == str(tmp_path / "x" / "seq1") and s.name == "seq1" and s.origin == "argument 1"


# -- manifest errors ---------------------------------------------------------------------------------------------
@pytest.mark.parametrize("text, needle", [
    ("- path: a\n  strid: 2\n", "unknown field 'strid'"),
    ("- name: a\n", "no 'path'"),
    ("- path: a\n  stride: 0\n", "stride: expected an integer >= 1"),
    ("- path: a\n  stride: two\n", "stride: expected an integer >= 1"),
    ("- path: a\n  calib: c.txt\n  intrinsics: [1, 1, 1, 1]\n", "either intrinsics or calib"),
    ("- path: a\n  intrinsics: [1, 2, 3]\n", "expected 4 numbers"),
    ("- path: a\n  lengths: [10, -5]\n", "positive"),
    ("- path: a\n  name: ../up\n", "cannot be a folder name"),
    ("- path: a\n  set: 3\n", "'set' must be"),
    ("- path: a\n  set: [sampling.seed]\n", "is not section.key=value"),
    ("sequences: []\n", "non-empty list"),
    ("seqs: [a]\n", "unknown top-level key 'seqs'"),
    ("- [a, b]\n", "must be a path or a mapping"),
])
def test_bad_yaml_manifest_names_file_and_problem(tmp_path, text, needle):
    m = _write(tmp_path / "m.yaml", text)
    with pytest.raises(ConfigError) as e:
        read_manifest(m)
    assert needle in str(e.value) and str(m) in str(e.value)


def test_invalid_yaml_gives_its_line(tmp_path):
    m = _write(tmp_path / "m.yaml", "- path: a\n- path: [b\n")
    with pytest.raises(ConfigError) as e:
        read_manifest(m)
    assert e.value.line is not None and "not valid YAML" in str(e.value)


@pytest.mark.parametrize("text, needle, line", [
    ("name,stride\na,2\n", "no 'path' column", 1),
    ("path,stride\na,2,9\n", "3 cells", 2),
    ("path\n", "no sequence rows", None),
    ("path,stride\na,x\n", "expected an integer", None),
])
def test_bad_csv_manifest(tmp_path, text, needle, line):
    m = _write(tmp_path / "m.csv", text)
    with pytest.raises(ConfigError) as e:
        read_manifest(m)
    assert needle in str(e.value)
    if line is not None:
        assert e.value.line == line


def test_manifest_suffix_and_missing_file(tmp_path):
    with pytest.raises(ConfigError, match="unknown manifest type"):
        read_manifest(_write(tmp_path / "m.txt", "a\n"))
    with pytest.raises(InputError, match="no such manifest"):
        read_manifest(tmp_path / "nope.yaml")


# -- sweeps ---------------------------------------------------------------------------------------------------
def test_split_values_respects_brackets_and_quotes():
    assert split_values("1,2,3") == ["1", "2", "3"]
    assert split_values("[128, 384],[192,640]") == ["[128, 384]", "[192,640]"]
    assert split_values("'a,b',c") == ["'a,b'", "c"]


def test_sweep_product_order_and_folders():
    sweeps = parse_sweeps(["sampling.seed=0,1", "keyframes.min_parallax_px=2,3,4.5"])
    combos = sweep_combinations(sweeps)
    assert len(combos) == 6
    assert combos[0] == (("sampling.seed", "0"), ("keyframes.min_parallax_px", "2"))
    assert combos[3] == (("sampling.seed", "1"), ("keyframes.min_parallax_px", "2"))  # first key slowest
    assert sweep_folder(combos[5]) == "sampling.seed=1,keyframes.min_parallax_px=4.5"
    assert sweep_folder((("input.size", "[128, 384]"),)) == "input.size=128_384"
    assert sweep_combinations([]) == [()]


@pytest.mark.parametrize("item, needle", [
    ("seed=1,2", "not section.key"), ("sampling.seed", "not section.key"), ("sampling.seed=1,,2", "empty value"),
    ("sampling.seed=1,1", "given twice"),
])
def test_bad_sweep(item, needle):
    with pytest.raises(ConfigError, match=needle):
        parse_sweeps([item])


def test_same_key_swept_twice_is_refused():
    with pytest.raises(ConfigError, match="swept twice"):
        parse_sweeps(["sampling.seed=1", "sampling.seed=2"])


# -- jobs ---------------------------------------------------------------------------------------------------
def _seqs(tmp_path, text):
    return read_manifest(_write(tmp_path / "m.yaml", text))


def test_expand_jobs_folders_and_override_order(tmp_path):
    seqs = _seqs(tmp_path, "- path: a\n  set: {sampling.seed: 7}\n  stride: 2\n- path: b\n  lengths: [5]\n")
    jobs = expand_jobs(seqs, overrides=["sampling.seed=1", "runtime.threads=1"],
                       sweeps=parse_sweeps(["sampling.n_samples=1000,2000"]), lengths=(50.0,), cwd=tmp_path)
    assert [j.out for j in jobs] == ["a/sampling.n_samples=1000", "a/sampling.n_samples=2000",
                                     "b/sampling.n_samples=1000", "b/sampling.n_samples=2000"]
    assert jobs[1].overrides == ("sampling.seed=1", "runtime.threads=1", "sampling.seed=7", "sampling.n_samples=2000")
    assert jobs[0].lengths == (50.0,) and jobs[2].lengths == (5.0,)  # the sequence's own win
    assert jobs[1].label == "a [sampling.n_samples=2000]"
    no_sweep = expand_jobs(seqs, cwd=tmp_path)
    assert [j.out for j in no_sweep] == ["a", "b"] and no_sweep[0].label == "a"


def test_config_file_made_absolute_preset_kept(tmp_path):
    (tmp_path / "c.yaml").write_text("sampling: {seed: 5}\n")
    seqs = sequences_from_args(["s"], cwd=tmp_path)
    assert expand_jobs(seqs, config_file="c.yaml", cwd=tmp_path)[0].config_file == str(tmp_path / "c.yaml")
    assert expand_jobs(seqs, config_file="kitti", cwd=tmp_path)[0].config_file == "kitti"


def test_duplicate_folders_refused(tmp_path):
    seqs = sequences_from_args(["x/seq", "y/seq"], cwd=tmp_path)
    with pytest.raises(ConfigError, match="output folder 'seq' is also that of argument 1"):
        expand_jobs(seqs, cwd=tmp_path)


def test_sweep_over_a_sequence_field_refused(tmp_path):
    seqs = _seqs(tmp_path, "- path: a\n  stride: 2\n")
    with pytest.raises(ConfigError, match="field 'stride' also sets it"):
        expand_jobs(seqs, sweeps=parse_sweeps(["input.stride=1,3"]), cwd=tmp_path)


def test_no_sequence_refused():
    with pytest.raises(ConfigError, match="no sequence"):
        expand_jobs([])


def test_job_config_equals_the_run_command_line(tmp_path):
    """The job's config is build_config of `run SEQ --config C --set (batch) --set (sequence) --set (sweep)
    --stride --gt`: the sequence's fields win over every --set, the sweep over the sequence's set."""
    cfg_file = tmp_path / "c.yaml"
    cfg_file.write_text(yaml.safe_dump({"sampling": {"seed": 9, "n_samples": 2500}, "input": {"stride": 7}}))
    seqs = _seqs(tmp_path, "- path: a\n  stride: 2\n  gt: a/poses.txt\n"
                           "  set: {sampling.n_samples: 3000, keyframes.min_parallax_px: 2.5}\n")
    (job,) = expand_jobs(seqs, config_file=str(cfg_file), overrides=["input.stride=5", "keyframes.min_parallax_px=1"],
                         sweeps=parse_sweeps(["keyframes.min_parallax_px=4"]), no_plot=True, cwd=tmp_path)
    got = job_config(job)
    want = build_config(str(cfg_file), ("input.stride=5", "keyframes.min_parallax_px=1", "sampling.n_samples=3000",
                                        "keyframes.min_parallax_px=2.5", "keyframes.min_parallax_px=4"),
                        {"stride": 2, "gt": str(tmp_path / "a" / "poses.txt")}, True)
    assert got == want
    assert (got.input.stride, got.sampling.seed, got.sampling.n_samples, got.keyframes.min_parallax_px) == \
        (2, 9, 3000, 4.0)
    assert str(got.output.gt) == str(tmp_path / "a" / "poses.txt") and got.output.plot is False


def test_job_config_bad_key_names_where(tmp_path):
    seqs = _seqs(tmp_path, "- path: a\n  set: {sampling.nope: 1}\n")
    (job,) = expand_jobs(seqs, sweeps=parse_sweeps(["sampling.seed=3"]), cwd=tmp_path)
    with pytest.raises(ConfigError) as e:
        job_config(job)
    text = str(e.value)
    assert "sampling.nope" in text and "sequence 1" in text and "sampling.seed=3" in text


def test_job_config_refuses_intrinsics_and_calib_together(tmp_path):
    job = Job(name="a", seq=str(tmp_path / "a"), out="a", overrides=("input.calib=c.txt",),
              fields=(("intrinsics", (700.0, 700.0, 600.0, 180.0)),), origin="argument 1")
    with pytest.raises(ConfigError, match="not both"):
        job_config(job)
