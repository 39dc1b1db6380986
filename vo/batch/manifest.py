"""What a batch runs: sequences (command line or a manifest) times sweep values -> a list of :class:`Job`.

Pure: reads the manifest file and nothing else (no sequence is opened here; a missing
sequence fails its own job, not the batch).

A manifest is YAML or CSV (by suffix: ``.yaml``/``.yml``, ``.csv``). Relative paths in it
are relative to the manifest's folder. YAML::

    sequences:                      # or the list itself at the top level
      - path: kitti06-f0000-0050    # the only required field
        name: k06                   # output folder DIR/NAME; default: the path's last part
        gt: kitti06-f0000-0050/poses.txt
        calib: calib.txt            # or intrinsics: [fx, fy, cx, cy] (not both)
        stride: 2                   # also start, end
        lengths: [10, 20, 30]       # KITTI segment lengths (m); default auto
        set:                        # configuration keys for this sequence only
          sampling.n_samples: 3000  # (or a list of "section.key=value")
      - kitti00-f0000-0150          # a bare path

CSV: a header row naming the same fields (``path`` required, any order); an empty cell
is "not given"; ``set`` is ``section.key=value`` items separated by ``;``; ``lengths`` and
``intrinsics`` are numbers separated by commas (quote the cell) or spaces.

Each sequence becomes one job per combination of the ``--sweep`` values (their cartesian
product, in the order given); its folder is ``DIR/NAME`` without a sweep and
``DIR/NAME/KEY=VALUE[,KEY=VALUE...]`` with one.

A job's configuration follows the ``run`` command's rule
(:func:`trianflow_vo.cli.config_flags.build_config`): defaults < ``--config`` < ``--set``
(the batch's, then the sequence's ``set``, then the sweep values) < the sequence's fields
(``stride``, ``gt``, ``calib``, ...), exactly as if they were ``run`` flags. A sweep over a key
that a sequence field also sets is refused (the field would win silently).
"""

from __future__ import annotations

import csv
import io
import itertools
import json
import os
import re
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path

from trianflow_vo.errors import ConfigError, InputError

# manifest field -> `run` shortcut flag name (trianflow_vo.cli.config_flags.SHORTCUTS)
SEQUENCE_FIELDS = {"gt": "gt", "calib": "calib", "intrinsics": "intrinsics", "stride": "stride", "start": "start",
                   "end": "end"}
FIELDS = ("path", "name", "lengths", "set", *SEQUENCE_FIELDS)
# the configuration key each sequence field sets (for the sweep collision check)
FIELD_KEYS = {"gt": "output.gt", "calib": "input.calib", "intrinsics": "input.intrinsics", "stride": "input.stride",
              "start": "input.start", "end": "input.end"}
_INT_FIELDS = {"stride": 1, "start": 0, "end": 1}  # field -> smallest value
_SAFE = re.compile(r"[^A-Za-z0-9._=+-]+")


@dataclass(frozen=True)
class SequenceEntry:
    """One sequence of a batch, as the command line or a manifest row gave it.

    Attributes:
        path: the sequence (absolute).
        name: its output folder name under ``DIR``.
        fields: ``run`` shortcut flags of this sequence, e.g. ``(("stride", 2), ("gt", "/abs/poses.txt"))``.
        overrides: ``section.key=value`` items of this sequence (after the batch's ``--set``).
        lengths: KITTI segment lengths (m), or None for automatic.
        origin: where it was given, for messages (``"manifest.yaml: sequence 2"``, ``"argument 1"``).
    """

    path: str
    name: str
    fields: tuple[tuple[str, object], ...] = ()
    overrides: tuple[str, ...] = ()
    lengths: tuple[float, ...] | None = None
    origin: str = ""


@dataclass(frozen=True)
class Job:
    """One run of a batch: a sequence with one combination of sweep values.

    Attributes:
        name: the sequence name (``DIR/NAME``).
        seq: the sequence path (absolute).
        out: the run folder relative to the batch folder: ``NAME`` or ``NAME/KEY=VALUE,...``.
        config_file: the batch's ``--config`` (a file made absolute, or a preset name), or None.
        overrides: every ``section.key=value``, applied in order: the batch's ``--set``, the
            sequence's ``set``, the sweep values.
        fields: the sequence's ``run`` shortcut flags (win over ``overrides``, as on ``run``).
        sweep: ``((key, value text), ...)`` of this job's sweep combination (empty without a sweep).
        lengths: KITTI segment lengths (m), or None for automatic.
        no_plot: no ``trajectory.png`` (``run --no-plot``).
        origin: where the sequence was given, for messages.
    """

    name: str
    seq: str
    out: str
    config_file: str | None = None
    overrides: tuple[str, ...] = ()
    fields: tuple[tuple[str, object], ...] = ()
    sweep: tuple[tuple[str, str], ...] = ()
    lengths: tuple[float, ...] | None = None
    no_plot: bool = False
    origin: str = field(default="", compare=False)

    @property
    def label(self) -> str:
        """``NAME`` or ``NAME [key=value, ...]``: how the job is named in messages and the summary."""
        return self.name if not self.sweep else f"{self.name} [{', '.join(f'{k}={v}' for k, v in self.sweep)}]"

    def shortcuts(self) -> dict:
        """The sequence's fields as the keyword values ``build_config`` takes for ``run``'s flags."""
        return dict(self.fields)


# -- sweeps -----------------------------------------------------------------------------------------------------
def split_values(text: str) -> list[str]:
    """``"1,2,[3, 4]"`` -> ``["1", "2", "[3, 4]"]``: commas split, except inside brackets or quotes."""
    out, cur, depth, quote = [], [], 0, None
    for ch in text:
        if quote:
            quote = None if ch == quote else quote
        elif ch in "'\"":
            quote = ch
        elif ch in "[{(":
            depth += 1
        elif ch in "]})":
            depth -= 1
        elif ch == "," and depth == 0:
            out.append("".join(cur).strip())
            cur = []
            continue
        cur.append(ch)
    out.append("".join(cur).strip())
    return out


def parse_sweeps(items: Sequence[str], source: str = "--sweep") -> list[tuple[str, list[str]]]:
    """``["sampling.seed=0,1", ...]`` -> ``[("sampling.seed", ["0", "1"]), ...]``.

    Raises:
        ConfigError: not ``section.key=v1,v2,...``, an empty value, a value given twice, a key swept twice.
    """
    out: list[tuple[str, list[str]]] = []
    for item in items:
        left, eq, right = str(item).partition("=")
        key = left.strip()
        section, dot, name = key.partition(".")
        if not eq or not dot or not section or not name:
            raise ConfigError(f"{item!r} is not section.key=v1,v2,... (e.g. sampling.seed=0,1,2)", source)
        values = split_values(right)
        if any(v == "" for v in values):
            raise ConfigError(f"empty value in {right!r}", source, key)
        if len(set(values)) != len(values):
            raise ConfigError(f"a value is given twice in {right!r}", source, key)
        if any(k == key for k, _ in out):
            raise ConfigError("swept twice; give all its values in one --sweep", source, key)
        out.append((key, values))
    return out


def sweep_combinations(sweeps: Sequence[tuple[str, Sequence[str]]]) -> list[tuple[tuple[str, str], ...]]:
    """Cartesian product of the sweep values, the first key varying slowest; ``[()]`` without a sweep."""
    keys = [k for k, _ in sweeps]
    return [tuple(zip(keys, combo)) for combo in itertools.product(*(v for _, v in sweeps))]


def sweep_folder(combo: Sequence[tuple[str, str]]) -> str:
    """The folder name of one sweep combination: ``key=value,key=value`` with unsafe characters as ``_``."""
    parts = []
    for k, v in combo:
        safe = _SAFE.sub("_", v).strip("_") or "_"
        parts.append(f"{k}={safe}")
    return ",".join(parts)


# -- sequences --------------------------------------------------------------------------------------------------
def _check_name(name: str, origin: str) -> str:
    name = str(name).strip()
    if not name or name in (".", "..") or "/" in name or "\\" in name or name.startswith("."):
        raise ConfigError(f"name {name!r} cannot be a folder name (no '/', not empty, not starting with '.')",
                          origin, "name")
    return name


def _resolve(path: str | Path, base: Path) -> str:
    p = Path(str(path)).expanduser()
    return os.path.abspath(p if p.is_absolute() else base / p)  # absolute and normalised (no "..")


def _numbers(value, origin: str, key: str, count: int | None = None) -> tuple[float, ...]:
    if isinstance(value, str):
        parts = [p for p in re.split(r"[,;\s]+", value.strip()) if p]
    elif isinstance(value, (list, tuple)):
        parts = list(value)
    else:
        parts = [value]
    try:
        nums = tuple(float(p) for p in parts)
    except (TypeError, ValueError):
        raise ConfigError(f"expected numbers, got {value!r}", origin, key) from None
    if not nums or (count is not None and len(nums) != count):
        want = f"{count} numbers" if count else "at least one number"
        raise ConfigError(f"expected {want}, got {value!r}", origin, key)
    return nums


def _lengths(value, origin: str) -> tuple[float, ...] | None:
    if value is None or (isinstance(value, str) and value.strip().lower() in ("", "auto")):
        return None
    nums = _numbers(value, origin, "lengths")
    if any(not (0 < x < float("inf")) for x in nums):
        raise ConfigError(f"segment lengths must be positive numbers, got {value!r}", origin, "lengths")
    return tuple(sorted(set(nums)))


def _overrides(value, origin: str) -> tuple[str, ...]:
    """A sequence's ``set``: a mapping ``{dotted key: value}``, a list of ``key=value``, or ``a=1;b=2`` text."""
    if value is None:
        return ()
    if isinstance(value, Mapping):
        out = []
        for k, v in value.items():
            # JSON is YAML: apply_overrides reads the value back exactly (strings quoted, lists, null)
            out.append(f"{k}={json.dumps(v)}")
        return tuple(out)
    if isinstance(value, str):
        items = [s.strip() for s in value.split(";") if s.strip()]
    elif isinstance(value, (list, tuple)):
        items = [str(s).strip() for s in value]
    else:
        raise ConfigError(f"'set' must be a mapping of section.key: value or a list of section.key=value, "
                          f"got {value!r}", origin, "set")
    for s in items:
        if "=" not in s:
            raise ConfigError(f"{s!r} is not section.key=value", origin, "set")
    return tuple(items)


def sequence_from_fields(row: Mapping, base: Path, origin: str) -> SequenceEntry:
    """One manifest entry (a mapping of :data:`FIELDS`) -> :class:`SequenceEntry`; paths relative to ``base``.

    Raises:
        ConfigError: an unknown field, no ``path``, a bad value, both ``calib`` and ``intrinsics``.
    """
    unknown = [k for k in row if k not in FIELDS]
    if unknown:
        raise ConfigError(f"unknown field {unknown[0]!r}; valid fields: {', '.join(FIELDS)}", origin)
    path = row.get("path")
    if path is None or str(path).strip() == "":
        raise ConfigError("no 'path' (the sequence folder or video)", origin)
    path = _resolve(str(path).strip(), base)
    name = _check_name(row["name"] if row.get("name") not in (None, "") else Path(path).name, origin)
    fields: list[tuple[str, object]] = []
    for f, flag in SEQUENCE_FIELDS.items():
        v = row.get(f)
        if v is None or (isinstance(v, str) and v.strip() == ""):
            continue
        if f in ("gt", "calib"):
            v = _resolve(str(v).strip(), base)
        elif f == "intrinsics":
            v = _numbers(v, origin, f, 4)
        else:
            try:
                v = int(str(v).strip()) if not isinstance(v, bool) else None
            except ValueError:
                v = None
            if v is None or v < _INT_FIELDS[f]:
                raise ConfigError(f"expected an integer >= {_INT_FIELDS[f]}, got {row.get(f)!r}", origin, f)
        fields.append((flag, v))
    names = {f for f, _ in fields}
    if "calib" in names and "intrinsics" in names:
        raise ConfigError("give either intrinsics or calib, not both", origin)
    return SequenceEntry(path=path, name=name, fields=tuple(fields), overrides=_overrides(row.get("set"), origin),
                     lengths=_lengths(row.get("lengths"), origin), origin=origin)


def _yaml_entries(text: str, source: str) -> list[tuple[object, str]]:
    import yaml

    try:
        doc = yaml.safe_load(text)
    except yaml.YAMLError as e:
        mark = getattr(e, "problem_mark", None)
        problem = getattr(e, "problem", None) or str(e).splitlines()[0]
        raise ConfigError(f"not valid YAML: {problem}", source, line=None if mark is None else mark.line + 1) \
            from None
    if isinstance(doc, Mapping):
        extra = [k for k in doc if k != "sequences"]
        if extra:
            raise ConfigError(f"unknown top-level key {extra[0]!r}; expected 'sequences'", source)
        doc = doc.get("sequences")
    if not isinstance(doc, list) or not doc:
        raise ConfigError("expected a non-empty list of sequences (top level, or under 'sequences:')", source)
    return [(e, f"{source}: sequence {i}") for i, e in enumerate(doc, 1)]


def _csv_entries(text: str, source: str) -> list[tuple[object, str]]:
    rows = list(csv.reader(io.StringIO(text)))
    rows = [(i, r) for i, r in enumerate(rows, 1) if any(c.strip() for c in r) and not r[0].lstrip().startswith("#")]
    if not rows:
        raise ConfigError("empty; expected a header row (path,name,gt,...) and one row per sequence", source)
    (_, header), body = rows[0], rows[1:]
    header = [h.strip() for h in header]
    if "path" not in header:
        raise ConfigError(f"the header row has no 'path' column (got {', '.join(header)})", source, line=1)
    if not body:
        raise ConfigError("no sequence rows after the header", source)
    out = []
    for line, r in body:
        if len(r) > len(header):
            raise ConfigError(f"{len(r)} cells, the header has {len(header)}", source, line=line)
        out.append(({h: c.strip() for h, c in zip(header, r) if c.strip() != ""}, f"{source}:{line}"))
    return out


def read_manifest(path: str | Path) -> list[SequenceEntry]:
    """The sequences of a YAML or CSV manifest (see the module docstring), in file order.

    Raises:
        InputError: the file cannot be read.
        ConfigError: an unknown suffix, bad syntax, an unknown field or a bad value (naming the file,
            and the line for CSV).
    """
    p = Path(path)
    try:
        text = p.read_text(encoding="utf-8")
    except FileNotFoundError:
        raise InputError("no such manifest file", p) from None
    except (OSError, UnicodeDecodeError) as e:
        raise InputError(f"cannot read the manifest: {getattr(e, 'strerror', None) or e}", p) from None
    suffix = p.suffix.lower()
    if suffix in (".yaml", ".yml"):
        entries = _yaml_entries(text, str(p))
    elif suffix == ".csv":
        entries = _csv_entries(text, str(p))
    else:
        raise ConfigError(f"unknown manifest type {suffix or '(no suffix)'!r}; use .yaml, .yml or .csv", str(p))
    base = p.resolve().parent
    seqs = []
    for entry, origin in entries:
        if isinstance(entry, (str, Path)):
            entry = {"path": entry}
        if not isinstance(entry, Mapping):
            raise ConfigError(f"a sequence must be a path or a mapping of fields, got {entry!r}", origin)
        seqs.append(sequence_from_fields(entry, base, origin))
    return seqs


def sequences_from_args(paths: Sequence[str | Path], cwd: Path | None = None) -> list[SequenceEntry]:
    """Sequences given on the command line (``SEQ...``), relative to ``cwd`` (default: the current folder)."""
    base = Path.cwd() if cwd is None else Path(cwd)
    return [sequence_from_fields({"path": str(s)}, base, f"argument {i}") for i, s in enumerate(paths, 1)]


# -- jobs -------------------------------------------------------------------------------------------------------
def _config_file(config_file: str | None, cwd: Path) -> str | None:
    """A ``--config`` that is an existing file, made absolute (workers may run elsewhere); a preset name as is."""
    if config_file is None:
        return None
    p = Path(config_file).expanduser()
    if not p.is_absolute() and (cwd / p).is_file():
        return os.path.abspath(cwd / p)
    return str(config_file)


def expand_jobs(
    sequences: Sequence[SequenceEntry],
    *,
    config_file: str | None = None,
    overrides: Sequence[str] = (),
    sweeps: Sequence[tuple[str, Sequence[str]]] = (),
    lengths: Sequence[float] | None = None,
    no_plot: bool = False,
    cwd: Path | None = None,
) -> list[Job]:
    """Every sequence times every sweep combination, in order (sequence-major).

    Args:
        sequences: from :func:`read_manifest` / :func:`sequences_from_args`.
        config_file: the batch's ``--config``.
        overrides: the batch's ``--set`` items (before each sequence's own).
        sweeps: from :func:`parse_sweeps`.
        lengths: the batch's KITTI segment lengths (a sequence's own win), or None for automatic.
        no_plot: no ``trajectory.png``.

    Raises:
        ConfigError: no sequence; two jobs with the same folder (give ``name`` in a manifest); a sweep
            over a key a sequence field also sets.
    """
    if not sequences:
        raise ConfigError("no sequence: give SEQ arguments or --manifest FILE", "batch")
    base = Path.cwd() if cwd is None else Path(cwd)
    cfg = _config_file(config_file, base)
    combos = sweep_combinations(sweeps)
    jobs: list[Job] = []
    seen: dict[str, str] = {}
    for s in sequences:
        field_keys = {FIELD_KEYS[f]: f for f, _ in ((f, v) for f, v in s.fields)}
        for key, _ in sweeps:
            if key in field_keys:
                raise ConfigError(f"swept, but the sequence's field {field_keys[key]!r} also sets it (and would "
                                  "win); remove one", s.origin, key)
        for combo in combos:
            out = s.name if not combo else f"{s.name}/{sweep_folder(combo)}"
            if out in seen:
                raise ConfigError(f"output folder {out!r} is also that of {seen[out]}; give each sequence its own "
                                  "'name' (in a manifest)", s.origin)
            seen[out] = s.origin
            jobs.append(Job(
                name=s.name, seq=s.path, out=out, config_file=cfg,
                overrides=(*overrides, *s.overrides, *(f"{k}={v}" for k, v in combo)),
                fields=s.fields, sweep=tuple(combo),
                lengths=s.lengths if s.lengths is not None else (None if lengths is None else tuple(lengths)),
                no_plot=no_plot, origin=s.origin))
    return jobs
