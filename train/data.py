"""Training data: pairs of frames ``(i, i + gap)`` from the input sequences, ready for the networks.

:func:`open_training_sources` turns each path into one or more :class:`Source`\\ s:

* a KITTI raw drive (``<date>_drive_<NNNN>_sync`` with ``image_02/data``), a date folder
  (all its drives) or the raw root (all dates), K from ``P_rect_02`` of the date folder's
  ``calib_cam_to_cam.txt`` (:mod:`trianflow_vo.io.kitti_raw`);
* a KITTI odometry sequence, a ``sequences/`` root (every sequence in it) or the odometry
  ``dataset/`` root holding ``sequences/``; leaving out test sequences is the caller's
  ``exclude``;
* a TUM RGB-D folder, an image folder with intrinsics, or a video;

all opened with :func:`trianflow_vo.io.sequence.open_sequence`, the reader ``run`` uses. A
source holds file names only, never images.

:class:`PairDataset` is a ``torch.utils.data.Dataset`` over every pair of every kept source.
A sample is::

    {"img1", "img2": (3, H, W) float32 tensors, BGR, in [0, 1],
     "K", "K_inv": (3, 3) float32 tensors at (H, W),
     "index": int (the pair), "flipped": bool}

or ``None`` when a frame of the pair cannot be read (the dataset never raises for a bad
sample; :func:`collate_pairs` counts them). Frames are resized to ``(H, W)`` with
``cv2.INTER_LINEAR`` and K scaled by the same factors, row by row (``fx, s, cx`` by
``W / W0``; ``fy, cy`` by ``H / H0``), as the authors do.

Horizontal flip (the authors' only augmentation): both images mirrored, ``x -> W - 1 - x``
(``cv2.flip``). Pixel ``x`` of the flipped image is pixel ``W - 1 - x`` of the original,
so with pixel centres at integer coordinates (OpenCV's, KITTI's and the losses' pixel
grids) the flipped camera is exactly ``cx' = W - 1 - cx`` (and skew ``s' = -s``) for the
mirrored scene. The authors flip the images and keep K unchanged, which is wrong by
``W - 1 - 2 cx`` pixels (about 1.5 px at 832 wide on KITTI); we mirror cx.

A flip is drawn from ``(seed, epoch, pair index)`` only (:meth:`PairDataset.flip_for`);
no global random state is touched.
"""

from __future__ import annotations

import fnmatch
import hashlib
import json
import logging
import math
from collections.abc import Callable, Iterable
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch

from trianflow_vo.errors import ConfigError, InputError
from trianflow_vo.frames import FrameSkip
from trianflow_vo.io import kitti_raw
from trianflow_vo.io.atomic import write_atomic
from trianflow_vo.io.sequence import FrameReader, Sequence, list_images, open_sequence

log = logging.getLogger("trianflow_vo")

EIGEN_TEST_SCENES = "eigen_test_scenes.txt"
PRESET_PACKAGE = "trianflow_vo.train.presets"
STATIC_CACHE_VERSION = 1
SAMPLE_KEYS = ("img1", "img2", "K", "K_inv")


# ---------------------------------------------------------------------------------------- sources


@dataclass(frozen=True)
class Source:
    """One training sequence.

    Attributes:
        name: what exclusions match: the drive folder name (``2011_09_26_drive_0001_sync``),
            the sequence folder name (``00``), the image folder name or the video file name.
        path: the folder or video, as :func:`open_sequence` accepts it.
        sequence: the opened :class:`~trianflow_vo.io.sequence.Sequence` (file list, K).
        ground_truth_path: the poses file when the source has one (KITTI ``poses.txt``
            inside or ``poses/<name>.txt`` of the odometry layout, TUM ``groundtruth.txt``,
            a clip's ``poses.txt``), else None.
    """

    name: str
    path: Path
    sequence: Sequence
    ground_truth_path: Path | None = None

    @property
    def kind(self) -> str:
        """``"kitti"``, ``"kitti_raw"``, ``"tum"``, ``"images"`` or ``"video"``."""
        return self.sequence.kind

    @property
    def K(self) -> np.ndarray:
        """``(3, 3)`` float64 intrinsics at the source resolution."""
        return self.sequence.K

    @property
    def image_size(self) -> tuple[int, int]:
        """``(H, W)`` of the source frames."""
        return self.sequence.image_size

    @property
    def frame_indices(self) -> range:
        """Source indices of the frames pairs are made of."""
        return self.sequence.indices

    def aliases(self) -> tuple[str, ...]:
        """The names an exclusion pattern is matched against: the name, the name without
        ``_sync`` (the Eigen lists' form) or without its suffix, ``<parent>/<name>`` and the path."""
        p = Path(self.path)
        out = [self.name, kitti_raw.drive_name(self.name), Path(self.name).stem, f"{p.parent.name}/{p.name}",
               p.as_posix()]
        return tuple(dict.fromkeys(out))


def has_ground_truth(source: Source) -> bool:
    """True when ``source`` has a poses file (:attr:`Source.ground_truth_path`)."""
    return source.ground_truth_path is not None


def _ground_truth(seq: Sequence) -> Path | None:
    gt = seq.ground_truth_path()
    if gt is not None:
        return gt
    if seq.kind == "tum" and (seq.path / "groundtruth.txt").is_file():
        return seq.path / "groundtruth.txt"
    if seq.kind == "kitti":  # the odometry layout: dataset/sequences/00 and dataset/poses/00.txt
        cand = seq.path.parent.parent / "poses" / f"{seq.path.name}.txt"
        if cand.is_file():
            return cand
    return None


def _is_kitti_odometry(folder: Path) -> bool:
    return any((folder / n).is_dir() for n in ("image_2", "image_0"))


def _expand(p: Path) -> list[Path]:
    """The sequence paths a training path stands for (a root or date folder -> its sequences)."""
    if not p.is_dir() or (p / "rgb.txt").is_file() or _is_kitti_odometry(p) or list_images(p):
        return [p]
    drives = kitti_raw.find_drives(p)
    if drives:
        return drives
    root = p / "sequences" if (p / "sequences").is_dir() else p
    subs = sorted((d for d in root.iterdir() if d.is_dir() and not d.name.startswith(".")), key=lambda d: d.name)
    odo = [d for d in subs if _is_kitti_odometry(d)]
    if odo:
        return odo
    if any(kitti_raw.is_drive(d) and kitti_raw.is_extract_drive(d) for d in subs):
        raise InputError("holds only unrectified KITTI raw drives (_extract); give the _sync drives", p)
    return [p]


def open_training_sources(
    paths: Iterable[str | Path],
    *,
    intrinsics: tuple[float, float, float, float] | None = None,
    calib: str | Path | None = None,
) -> list[Source]:
    """Open every training path as one or more sources (see the module docstring).

    Args:
        paths: KITTI raw drive / date / root folders, KITTI odometry sequences or roots, TUM
            folders, image folders or videos.
        intrinsics: ``(fx, fy, cx, cy)`` at source resolution for every source (overrides
            their own calibration), as ``run --intrinsics``.
        calib: a calibration file for every source, as ``run --calib``.

    Returns:
        the sources in the order given (a root's sequences in name order); a sequence
        reached twice (e.g. a drive and its date folder) is kept once.

    Raises:
        InputError: naming the path: nothing given, no such path, no images, no calibration
            (with how to give it), an unknown format, fewer than two frames.
    """
    if isinstance(paths, (str, Path)):
        paths = [paths]
    paths = list(paths)
    if not paths:
        raise InputError("no training data given")
    out: list[Source] = []
    seen: set[Path] = set()
    for raw in paths:
        p = Path(raw)
        if not p.exists():
            raise InputError("no such file or folder", p)
        for q in _expand(p):
            seq = open_sequence(q, intrinsics=intrinsics, calib=calib)
            key = seq.path.resolve()
            if key in seen:
                continue
            seen.add(key)
            out.append(Source(seq.path.name, seq.path, seq, _ground_truth(seq)))
    return out


def eigen_test_scenes() -> list[str]:
    """The KITTI raw drives of the Eigen test split (``2011_09_26_drive_0002``, ...), from
    the shipped ``train/presets/eigen_test_scenes.txt``."""
    from importlib.resources import files

    text = files(PRESET_PACKAGE).joinpath(EIGEN_TEST_SCENES).read_text()
    return [s.strip() for s in text.splitlines() if s.strip() and not s.lstrip().startswith("#")]


def excluded(source: Source, patterns: Iterable[str]) -> str | None:
    """The first pattern (exact name or glob, case-sensitive) matching one of the source's
    :meth:`~Source.aliases`, else None."""
    names = source.aliases()
    for pat in patterns:
        if any(fnmatch.fnmatchcase(n, pat) for n in names):
            return pat
    return None


# ---------------------------------------------------------------------------------------- images and K


def scale_intrinsics(K: np.ndarray, src_hw: tuple[int, int], dst_hw: tuple[int, int]) -> np.ndarray:
    """K of a frame resized from ``src_hw`` to ``dst_hw`` (both ``(H, W)``): the first row
    (``fx, s, cx``) times ``W / W0``, the second (``fy, cy``) times ``H / H0``.

    Args:
        K: ``(3, 3)`` intrinsics at ``src_hw``.

    Returns:
        ``(3, 3)`` float64.
    """
    out = np.array(K, dtype=np.float64, copy=True)
    out[0] *= dst_hw[1] / src_hw[1]
    out[1] *= dst_hw[0] / src_hw[0]
    return out


def flip_intrinsics(K: np.ndarray, width: int) -> np.ndarray:
    """K of a horizontally mirrored image ``width`` pixels wide (pixel ``x -> width - 1 - x``):
    ``cx' = width - 1 - cx`` and skew ``s' = -s``, for the scene mirrored in ``X``.

    Args:
        K: ``(3, 3)`` intrinsics of the unflipped image.

    Returns:
        ``(3, 3)`` float64.
    """
    out = np.array(K, dtype=np.float64, copy=True)
    out[0, 1] = -out[0, 1]
    out[0, 2] = width - 1 - out[0, 2]
    return out


def prepare_image(image: np.ndarray, size: tuple[int, int], flip: bool = False) -> np.ndarray:
    """Network input of one frame.

    Args:
        image: ``(H0, W0, 3)`` uint8 BGR.
        size: ``(H, W)`` to resize to (``cv2.INTER_LINEAR``).
        flip: mirror horizontally after resizing.

    Returns:
        ``(3, H, W)`` float32 BGR in [0, 1], contiguous.
    """
    import cv2

    h, w = size
    img = image if image.shape[:2] == (h, w) else cv2.resize(image, (w, h), interpolation=cv2.INTER_LINEAR)
    if flip:
        img = cv2.flip(img, 1)
    return np.ascontiguousarray(img.transpose(2, 0, 1), dtype=np.float32) / np.float32(255.0)


# ---------------------------------------------------------------------------------------- static filter


def median_flow_px(grey1: np.ndarray, grey2: np.ndarray, sx: float = 1.0, sy: float = 1.0) -> float:
    """Median magnitude of the OpenCV DIS flow (medium preset) from ``grey1`` to ``grey2``.

    Args:
        grey1, grey2: ``(h, w)`` uint8 (made contiguous here, as DIS requires).
        sx, sy: factors applied to the flow's x and y components before the magnitude
            (to express it in pixels of a larger image).

    Returns:
        the median of ``|(sx * dx, sy * dy)|`` over the image.
    """
    import cv2

    dis = cv2.DISOpticalFlow.create(cv2.DISOPTICAL_FLOW_PRESET_MEDIUM)
    flow12 = dis.calc(np.ascontiguousarray(grey1, dtype=np.uint8), np.ascontiguousarray(grey2, dtype=np.uint8), None)
    return float(np.median(np.hypot(flow12[..., 0] * sx, flow12[..., 1] * sy)))


def _small_grey(image: np.ndarray, small_hw: tuple[int, int]) -> np.ndarray:
    import cv2

    h, w = small_hw
    grey = cv2.cvtColor(image, cv2.COLOR_BGR2GRAY)
    return np.ascontiguousarray(cv2.resize(grey, (w, h), interpolation=cv2.INTER_AREA))


def _small_size(size: tuple[int, int], scale: float) -> tuple[int, int]:
    return max(16, int(round(size[0] * scale))), max(16, int(round(size[1] * scale)))


def _file_entries(source: Source) -> list[tuple[str, int]]:
    """``(name, bytes)`` of each source file (the video itself for a video); -1 if unreadable."""
    seq = source.sequence
    files = seq.files
    if files is None:
        files = (Path(seq.path),)
        base = Path(seq.path).parent
    else:
        base = seq.image_dir or Path(seq.path)
    out = []
    for f in files:
        try:
            n = f.stat().st_size
        except OSError:
            n = -1
        try:
            name = f.relative_to(base).as_posix()
        except ValueError:
            name = f.name
        out.append((name, n))
    return out


def pair_flow_medians(
    source: Source,
    pairs: np.ndarray,
    size: tuple[int, int],
    scale: float = 0.25,
    progress: Callable[[str, int, int], None] | None = None,
) -> np.ndarray:
    """Median DIS flow magnitude of each pair, in pixels at the training size.

    Each frame is decoded once (a pair's second frame is kept for the next pairs), turned
    grey and resized to ``scale`` times the training size for DIS; the flow is scaled back.

    Args:
        source: the sequence.
        pairs: ``(P, 2)`` int source indices ``(i1, i2)``.
        size: training ``(H, W)``.
        scale: DIS resolution relative to ``size``.
        progress: ``progress(source.name, done, total)`` after each pair.

    Returns:
        ``(P,)`` float64, NaN where a frame cannot be read.
    """
    pairs = np.asarray(pairs, dtype=np.int64).reshape(-1, 2)
    small = _small_size(size, scale)
    sy, sx = size[0] / small[0], size[1] / small[1]
    reader = FrameReader(source.sequence)
    cache: dict[int, np.ndarray | None] = {}
    out = np.full(len(pairs), np.nan)
    try:
        for n, (i1, i2) in enumerate(pairs):
            for i in (int(i1), int(i2)):
                if i not in cache:
                    fr = reader.read(i)
                    cache[i] = None if isinstance(fr, FrameSkip) else _small_grey(fr.image, small)
            g1, g2 = cache[int(i1)], cache[int(i2)]
            if g1 is not None and g2 is not None:
                out[n] = median_flow_px(g1, g2, sx, sy)
            lo = int(i1)
            for k in [k for k in cache if k < lo]:
                del cache[k]
            if progress is not None:
                progress(source.name, n + 1, len(pairs))
    finally:
        reader.close()
    return out


def static_pairs(
    source: Source,
    pairs: np.ndarray,
    size: tuple[int, int],
    *,
    threshold_px: float = 1.0,
    scale: float = 0.25,
    cache_dir: str | Path | None = None,
    progress: Callable[[str, int, int], None] | None = None,
) -> np.ndarray:
    """Which pairs are static: median DIS flow (training-size pixels) below ``threshold_px``.

    The medians are computed once per (source files, pairs, size, scale) and cached as
    JSON in ``cache_dir`` (``static-<name>-<key>.json``, written atomically); the threshold
    is applied after reading, so another threshold reuses the cache. A pair whose frames
    cannot be read is not static (the dataset gives None for it later).

    Args:
        source: the sequence.
        pairs: ``(P, 2)`` int source indices.
        size: training ``(H, W)``.
        threshold_px: pixels at the training size.
        scale: DIS resolution relative to ``size``.
        cache_dir: where the cache lives; None: no cache.
        progress: ``progress(source.name, done, total)`` while computing.

    Returns:
        ``(P,)`` bool, True = static (to drop).
    """
    pairs = np.asarray(pairs, dtype=np.int64).reshape(-1, 2)
    if len(pairs) == 0:
        return np.zeros(0, dtype=bool)
    medians = None
    cache = None
    if cache_dir is not None:
        h = hashlib.sha256()
        h.update(json.dumps({"v": STATIC_CACHE_VERSION, "size": list(size), "scale": float(scale),
                             "flow": "dis-medium", "image_size": list(source.image_size)}).encode())
        for name, n in _file_entries(source):
            h.update(f"{name}\0{n}\n".encode())
        h.update(pairs.tobytes())
        safe = "".join(c if c.isalnum() or c in "-_." else "_" for c in source.name)[:60]
        cache = Path(cache_dir) / f"static-{safe}-{h.hexdigest()[:20]}.json"
        if cache.is_file():
            try:
                doc = json.loads(cache.read_text())
                got = np.array([np.nan if m is None else m for m in doc["median_px"]], dtype=np.float64)
                if got.shape == (len(pairs),):
                    medians = got
            except (OSError, ValueError, KeyError, TypeError):
                medians = None  # unreadable cache: recompute and overwrite
            if medians is None:
                log.warning(f"{cache}: unreadable static-filter cache, recomputing")
    if medians is None:
        medians = pair_flow_medians(source, pairs, size, scale, progress)
        if cache is not None:
            cache.parent.mkdir(parents=True, exist_ok=True)
            doc = {"version": STATIC_CACHE_VERSION, "source": str(source.path), "size": list(size),
                   "scale": float(scale), "pairs": pairs.tolist(),
                   "median_px": [None if not math.isfinite(m) else round(float(m), 4) for m in medians]}
            write_atomic(cache, (json.dumps(doc) + "\n").encode())
    return np.isfinite(medians) & (medians < float(threshold_px))


@dataclass(frozen=True)
class StaticFilter:
    """The optional static-pair filter of :class:`PairDataset` (see :func:`static_pairs`).

    Attributes:
        threshold_px: a pair whose median DIS flow is below this (pixels at the training
            size) is dropped.
        cache_dir: where the per-source medians are cached (None: not cached).
        scale: DIS resolution relative to the training size.
        progress: optional ``progress(source_name, done, total)``.
    """

    threshold_px: float = 1.0
    cache_dir: Path | None = None
    scale: float = 0.25
    progress: Callable[[str, int, int], None] | None = None

    def __post_init__(self):
        if not (isinstance(self.threshold_px, (int, float)) and math.isfinite(self.threshold_px)
                and self.threshold_px >= 0):
            raise ConfigError(f"must be a number >= 0, got {self.threshold_px!r}", key="data.static_threshold_px")
        if not (isinstance(self.scale, (int, float)) and 0 < self.scale <= 1):
            raise ConfigError(f"must be in (0, 1], got {self.scale!r}", key="static filter scale")

    def static(self, source: Source, pairs: np.ndarray, size: tuple[int, int]) -> np.ndarray:
        """``(P,)`` bool, True for the static pairs of ``pairs`` (``(P, 2)`` source indices)."""
        return static_pairs(source, pairs, size, threshold_px=self.threshold_px, scale=self.scale,
                            cache_dir=self.cache_dir, progress=self.progress)

    def describe(self) -> dict:
        """The settings that decide which pairs are kept (part of :func:`fingerprint`)."""
        return {"threshold_px": float(self.threshold_px), "scale": float(self.scale), "flow": "dis-medium"}


# ---------------------------------------------------------------------------------------- dataset


def _check_size(size) -> tuple[int, int]:
    try:
        h, w = (int(v) for v in size)
        ok = all(float(v) == int(v) for v in size) and h > 0 and w > 0
    except (TypeError, ValueError):
        ok = False
    if not ok:
        raise ConfigError(f"expected two positive integers (H, W), got {size!r}", key="data.size")
    return h, w


def _mix64(*values: int) -> list[int]:
    return [int(v) % (1 << 64) for v in values]


class PairDataset(torch.utils.data.Dataset):
    """Random access to the pairs ``(i, i + gap)`` of every kept source.

    Args:
        sources: from :func:`open_training_sources`.
        size: training ``(H, W)``.
        gap: frames between the two images of a pair (>= 1), counted in the source's
            selected frames.
        flip: draw a horizontal flip with probability 0.5 per sample in ``dataset[k]``.
        exclude: names or glob patterns; a source matching one (:func:`excluded`) is left out.
        static_filter: drop static pairs (computed here, once, cached).
        seed: seed of the flips.

    Attributes:
        sources: the kept sources; ``excluded_sources``: ``(name, pattern)`` of those left
        out; ``unused_exclusions``: patterns that matched no source (a typo?);
        ``n_static``: pairs dropped by the static filter.

    Indexing: ``dataset[k]`` (flip drawn from ``(seed, 0, k)``), ``dataset[(k, epoch)]``, or
    :meth:`get` with an explicit flip. Workers: the dataset pickles without open video
    captures; each process opens its own on first read.
    """

    def __init__(
        self,
        sources: list[Source],
        size: tuple[int, int] = (256, 832),
        gap: int = 1,
        flip: bool = False,
        exclude: Iterable[str] = (),
        static_filter: StaticFilter | None = None,
        seed: int = 0,
    ):
        self.size = _check_size(size)
        if isinstance(gap, bool) or not isinstance(gap, (int, np.integer)) or gap < 1:
            raise ConfigError(f"must be an integer >= 1, got {gap!r}", key="data.gap")
        if isinstance(exclude, str):
            exclude = [exclude]
        exclude = tuple(exclude)
        for pat in exclude:
            if not isinstance(pat, str) or not pat.strip():
                raise ConfigError(f"exclusions must be non-empty names or patterns, got {pat!r}", key="data.exclude")
        for s in sources:
            if not isinstance(s, Source):
                raise InputError(f"not a training source (use open_training_sources): {s!r}")
        self.gap = int(gap)
        self.flip = bool(flip)
        self.seed = int(seed)
        self.exclude = exclude
        self.static_filter = static_filter
        kept, self.excluded_sources = [], []
        for s in sources:
            pat = excluded(s, exclude)
            if pat is None:
                kept.append(s)
            else:
                self.excluded_sources.append((s.name, pat))
        self.unused_exclusions = [p for p in exclude if not excluded_any(p, sources)]
        self.sources = kept
        self._firsts: list[np.ndarray] = []  # per source: positions j in frame_indices of the pairs' first frames
        self.n_static = 0
        for s in kept:
            n = len(s.frame_indices)
            firsts = np.arange(max(0, n - self.gap), dtype=np.int64)
            if static_filter is not None and len(firsts):
                idx = np.asarray(s.frame_indices)
                drop = static_filter.static(s, np.stack([idx[firsts], idx[firsts + self.gap]], 1), self.size)
                self.n_static += int(drop.sum())
                firsts = firsts[~drop]
            self._firsts.append(firsts)
        self._offsets = np.concatenate([[0], np.cumsum([len(f) for f in self._firsts], dtype=np.int64)])
        self._readers = [FrameReader(s.sequence) for s in kept]

    def __len__(self) -> int:
        return int(self._offsets[-1])

    def pair(self, k: int) -> tuple[int, int, int]:
        """``(source number, i1, i2)`` of pair ``k``: source indices of its two frames."""
        if isinstance(k, bool) or not isinstance(k, (int, np.integer)):
            raise TypeError(f"pair index must be an integer, got {k!r}")
        if not 0 <= k < len(self):
            raise IndexError(f"pair {k} outside the dataset's {len(self)} pairs")
        s = int(np.searchsorted(self._offsets, k, side="right") - 1)
        j = int(self._firsts[s][k - self._offsets[s]])
        idx = self.sources[s].frame_indices
        return s, idx[j], idx[j + self.gap]

    def flip_for(self, k: int, epoch: int = 0) -> bool:
        """The flip of pair ``k`` in ``epoch``: False unless ``flip``; else a coin from
        ``(seed, epoch, k)`` alone."""
        if not self.flip:
            return False
        return bool(np.random.default_rng(_mix64(self.seed, epoch, k)).random() < 0.5)

    def _read(self, s: int, i: int) -> tuple[np.ndarray | None, str]:
        try:
            fr = self._readers[s].read(i)
        except Exception as e:  # a bad sample never ends a run
            return None, f"{self.sources[s].path}#{i}: {type(e).__name__}: {e}"
        if isinstance(fr, FrameSkip):
            return None, f"{fr.source}: {fr.reason}"
        return fr.image, ""

    def skip_reason(self, k: int) -> str | None:
        """Why pair ``k`` gives None (re-reads it), or None when it reads."""
        s, i1, i2 = self.pair(k)
        for i in (i1, i2):
            img, reason = self._read(s, i)
            if img is None:
                return reason
        return None

    def get(self, k: int, flip: bool | None = None, epoch: int = 0) -> dict | None:
        """Sample of pair ``k`` (see the module docstring), or None when a frame cannot be read.

        Args:
            k: pair index in ``range(len(self))`` (else ``IndexError``).
            flip: mirror it; None: :meth:`flip_for` ``(k, epoch)``.
            epoch: only for the drawn flip.
        """
        s, i1, i2 = self.pair(k)
        if flip is None:
            flip = self.flip_for(k, epoch)
        img1, _ = self._read(s, i1)
        if img1 is None:
            return None
        img2, _ = self._read(s, i2)
        if img2 is None:
            return None
        src = self.sources[s]
        try:
            K = scale_intrinsics(src.K, src.image_size, self.size)
            if flip:
                K = flip_intrinsics(K, self.size[1])
            a = prepare_image(img1, self.size, bool(flip))
            b = prepare_image(img2, self.size, bool(flip))
        except Exception as e:  # e.g. cv2.error on a degenerate frame
            log.debug(f"pair {k} of {src.path}: {e}")
            return None
        return {
            "img1": torch.from_numpy(a),
            "img2": torch.from_numpy(b),
            "K": torch.from_numpy(K.astype(np.float32)),
            "K_inv": torch.from_numpy(np.linalg.inv(K).astype(np.float32)),
            "index": int(k),
            "flipped": bool(flip),
        }

    def __getitem__(self, key) -> dict | None:
        if isinstance(key, tuple):
            k, epoch = key
            return self.get(k, epoch=epoch)
        return self.get(key)

    def describe(self) -> dict:
        """Counts for logs and ``status.json``."""
        return {"sources": len(self.sources), "pairs": len(self), "excluded": [n for n, _ in self.excluded_sources],
                "unused_exclusions": list(self.unused_exclusions), "static_dropped": self.n_static,
                "size": list(self.size), "gap": self.gap}


def excluded_any(pattern: str, sources: Iterable[Source]) -> bool:
    """True when ``pattern`` matches one of ``sources`` (see :func:`excluded`)."""
    return any(excluded(s, [pattern]) is not None for s in sources)


def collate_pairs(items: list[dict | None]) -> tuple[dict | None, int]:
    """``DataLoader`` ``collate_fn``: stack the readable samples, count the others.

    Args:
        items: samples of :meth:`PairDataset.get` (dicts) or None.

    Returns:
        ``(batch, n_skipped)``: ``batch`` has ``"img1"``/``"img2"`` ``(B, 3, H, W)``,
        ``"K"``/``"K_inv"`` ``(B, 3, 3)``, ``"index"`` ``(B,)`` int64, ``"flipped"``
        ``(B,)`` bool, or is None when every item was None.
    """
    good = [it for it in items if it is not None]
    skipped = len(items) - len(good)
    if not good:
        return None, skipped
    batch = {k: torch.stack([g[k] for g in good]) for k in SAMPLE_KEYS}
    batch["index"] = torch.tensor([int(g["index"]) for g in good], dtype=torch.int64)
    batch["flipped"] = torch.tensor([bool(g.get("flipped", False)) for g in good], dtype=torch.bool)
    return batch, skipped


def fingerprint(dataset: PairDataset) -> str:
    """16 hex digits identifying the training pairs: each kept source's kind, name, K and file
    list (names relative to the source, byte sizes), the pairs kept, size, gap, exclusions
    and static-filter settings. Moving the data elsewhere keeps it; changing a file's size,
    adding or removing frames or changing a setting changes it."""
    h = hashlib.sha256()
    static = None if dataset.static_filter is None else dataset.static_filter.describe()
    h.update(json.dumps({"v": 1, "size": list(dataset.size), "gap": dataset.gap,
                         "exclude": sorted(dataset.exclude), "static": static, "pairs": len(dataset)}).encode())
    for src, firsts in zip(dataset.sources, dataset._firsts):
        h.update(json.dumps({"kind": src.kind, "name": src.name, "K": np.round(src.K, 6).tolist(),
                             "image_size": list(src.image_size)}).encode())
        for name, n in _file_entries(src):
            h.update(f"{name}\0{n}\n".encode())
        h.update(np.ascontiguousarray(firsts, dtype=np.int64).tobytes())
    return h.hexdigest()[:16]
