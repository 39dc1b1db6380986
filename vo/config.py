"""The one configuration tree: frozen dataclasses, the only place defaults live.

:class:`Config` has one section per concern (``input``, ``flow``, ``depth``, ...),
each a frozen dataclass whose fields carry their default, a one-line help text and
their constraint. Every section validates (and normalises: ``str`` -> ``Path``,
list -> tuple, ``"256x832"`` -> ``(256, 832)``) in ``__post_init__``, so a bad value
raises :class:`ConfigError` (a ``ValueError``) however the config is built.

Files, presets and ``--set`` overrides go through :func:`load_config`,
:func:`merge_dict` and :func:`apply_overrides`; their errors name the file or option,
the dotted key and what is valid. Precedence in the CLI: defaults < ``--config`` <
``--set`` < explicit shortcut flags.

Only the standard library here; ``yaml`` is imported inside the functions that use it.
"""

from __future__ import annotations

import dataclasses
import math
import numbers
import os
import re
import types
import typing
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Literal, Union

from trianflow_vo.errors import ConfigError

__all__ = [
    "Config", "InputConfig", "FlowConfig", "DepthConfig", "SamplingConfig", "GeometryConfig", "ScaleConfig",
    "KeyframeConfig", "BackendConfig", "OutputConfig", "RuntimeConfig", "ConfigError",
    "config_from_dict", "load_config", "apply_overrides", "merge_dict", "write_config_yaml", "config_keys",
    "preset_names",
]

PRESET_PACKAGE = "trianflow_vo.configs"
HEADER = "# Effective configuration; reproduce the run with: trianflow-vo run SEQ --config THIS_FILE"


# -- field declarations -----------------------------------------------------------------------------------------
@dataclass(frozen=True)
class _Range:
    """A numeric interval; ``None`` = unbounded on that side."""

    lo: float | None = None
    hi: float | None = None
    lo_open: bool = False
    hi_open: bool = False

    def __contains__(self, v: float) -> bool:
        if self.lo is not None and not (v > self.lo if self.lo_open else v >= self.lo):
            return False
        if self.hi is not None and not (v < self.hi if self.hi_open else v <= self.hi):
            return False
        return True

    def text(self) -> str:
        """``(0, 1]`` when bounded on both sides, else ``>= 0`` / ``> 0`` / ``<= 9``."""
        if self.lo is not None and self.hi is not None:
            return f"{'(' if self.lo_open else '['}{_num(self.lo)}, {_num(self.hi)}{')' if self.hi_open else ']'}"
        if self.lo is not None:
            return f"{'>' if self.lo_open else '>='} {_num(self.lo)}"
        return f"{'<' if self.hi_open else '<='} {_num(self.hi)}"

    def error(self, v: float) -> str:
        if self.lo is not None and self.hi is not None:
            return f"{_show(v)} is out of range {self.text()}"
        return f"{_show(v)} is out of range; must be {self.text()}"


def _opt(default: Any, help: str, *, range: _Range | None = None, check: Callable[[Any], str | None] | None = None,
         rule: str = "", sep: str = "", form: str = "") -> Any:
    """A config field: ``default``, one-line ``help`` and its constraint.

    range: numeric interval of a scalar. check: ``value -> error message or None`` for
    anything else, described in docs by ``rule``. sep/form: a tuple field also accepts a
    string of its items joined by ``sep``; ``form`` is how docs write its type.
    """
    return field(default=default, metadata={"help": help, "range": range, "check": check, "rule": rule,
                                            "sep": sep, "form": form})


MAX_SIZE_SIDE = 4096  # largest working height or width (input.size)


def _multiples_of_64(hw: tuple[int, int]) -> str | None:
    if not all(v > 0 and v % 64 == 0 for v in hw):
        return f"{_show(list(hw))} is not two positive multiples of 64 (h, w), e.g. [256, 832] or '256x832'"
    if max(hw) > MAX_SIZE_SIDE:
        return f"{_show(list(hw))} is too large: the working size is at most {MAX_SIZE_SIDE} per side (h, w)"
    return None


def _positive_focal(k: tuple[float, float, float, float]) -> str | None:
    return None if k[0] > 0 and k[1] > 0 else f"{_show(list(k))} has fx or fy <= 0 (fx, fy, cx, cy; fx, fy > 0)"


def _ratio_or_off(v: float) -> str | None:
    return None if v == 0 or v > 1 else f"{_show(v)} is out of range; must be 0 (off) or > 1"


class _Section:
    """Base of the section dataclasses: validates and normalises every field after ``__init__``."""

    NAME = ""  # the section's key in Config, e.g. "input"

    def __post_init__(self) -> None:
        source = type(self).__name__
        hints = _hints(type(self))
        for f in dataclasses.fields(self):  # type: ignore[arg-type]
            v = getattr(self, f.name)
            nv = _check_value(hints[f.name], f.metadata, v, source, f"{self.NAME}.{f.name}")
            if nv is not v:
                object.__setattr__(self, f.name, nv)
        self._check_together(source)

    def _check_together(self, source: str) -> None:
        """Constraints between fields of the section (none by default)."""


@dataclass(frozen=True)
class InputConfig(_Section):
    """Which frames to read and the camera."""

    NAME = "input"
    start: int = _opt(0, "first source frame index to read", range=_Range(0))
    end: int | None = _opt(None, "source frame index to stop before (exclusive); null = to the end",
                           rule="> input.start")
    stride: int = _opt(1, "read every stride-th source frame", range=_Range(1))
    size: tuple[int, int] | None = _opt(None, "working (h, w) the frames are resized to; null = automatic",
                                        check=_multiples_of_64, rule="positive multiples of 64, at most 4096", sep="x",
                                        form="HxW or [h, w]")
    intrinsics: tuple[float, float, float, float] | None = _opt(
        None, "camera fx, fy, cx, cy in pixels at source resolution; null = from input.calib or the sequence",
        check=_positive_focal, rule="fx, fy > 0", sep=",", form="fx,fy,cx,cy or [fx, fy, cx, cy]")
    calib: Path | None = _opt(
        None, "calibration file: KITTI calib.txt, a 3x3 K or 'fx fy cx cy'; null = the sequence's own")
    readout: float = _opt(0.0, "rolling shutter: time from reading the top row to the bottom row, in source frame "
                               "intervals (0 = global shutter; negative = rows read bottom to top); each match is "
                               "moved to its frame's middle-row instant with the motion of the last frame step",
                          range=_Range(-1.0, 1.0))

    def _check_together(self, source: str) -> None:
        if self.end is not None and self.end <= self.start:
            raise ConfigError(f"{self.end} must be greater than input.start ({self.start})", source, "input.end")


@dataclass(frozen=True)
class FlowConfig(_Section):
    """Optical flow between the keyframe and the current frame."""

    NAME = "flow"
    model: Path | None = _opt(None, "ONNX optical-flow network; null = OpenCV DIS flow (no weights)")
    dis_preset: Literal["fast", "medium", "fine"] = _opt("medium", "OpenCV DIS preset when flow.model is null")
    ahead: bool = _opt(True, "DIS flow: compute the next frame's flow in a background thread while the current "
                             "frame is solved (against the keyframe it will most likely have; the same results, "
                             "less time per frame)")


@dataclass(frozen=True)
class DepthConfig(_Section):
    """Keyframe depth: a network or carried from triangulation, fused along rays."""

    NAME = "depth"
    model: Path | None = _opt(None, "ONNX depth network; null = depth carried from triangulation")
    fusion: bool = _opt(True, "fuse the carried depth with each new triangulation along the rays")
    decay: float = _opt(0.8, "weight the carried depth keeps per keyframe step",
                        range=_Range(0.0, 1.0, lo_open=True))
    max_log_gap: float = _opt(0.3, "largest |log(carried / new depth)| that is fused; larger gaps take the new",
                              range=_Range(0.0, lo_open=True))


@dataclass(frozen=True)
class SamplingConfig(_Section):
    """Which flow matches are drawn per frame pair."""

    NAME = "sampling"
    n_samples: int = _opt(12000, "flow matches drawn per frame pair (measured, seeds 0-11: 12000 instead of 6000 "
                                 "takes 7-Scenes stride 3 from 1.58 to 1.18 % ATE, costs ~10 % of the frame "
                                 "rate and leaves one TUM teddy seed worse; README, back-end)",
                           range=_Range(100, 100000))
    top_ratio: float = _opt(0.2, "fraction of best-scored pixels the matches are drawn from",
                            range=_Range(0.0, 1.0, lo_open=True))
    max_anchors: int = _opt(6000, "most sparse-depth pixels used as PnP anchors", range=_Range(0))
    seed: int = _opt(0, "random seed of sampling and RANSAC (runs are reproducible)", range=_Range(0))


@dataclass(frozen=True)
class GeometryConfig(_Section):
    """Two-view geometry, triangulation and PnP."""

    NAME = "geometry"
    ransac_method: Literal["ransac", "magsac", "8point"] = _opt(
        "ransac", "fundamental-matrix estimator: OpenCV RANSAC, MAGSAC++ or plain 8-point")
    ransac_threshold_px: float = _opt(0.25, "RANSAC inlier threshold in pixels", range=_Range(0.0, lo_open=True))
    ransac_subset: int = _opt(1000, "matches drawn at random for RANSAC when refine is on", range=_Range(8))
    refine: bool = _opt(True, "refine the fundamental matrix on all inliers after RANSAC")
    epi_inlier_px: float = _opt(0.5, "Sampson distance in pixels under which a match is an inlier",
                                range=_Range(0.0, lo_open=True))
    min_inliers: int = _opt(100, "fewest reliable matches / inliers to accept a frame pair", range=_Range(8))
    min_angle_rad: float = _opt(1e-3, "triangulated rays meeting at a smaller angle (radians) are dropped",
                                range=_Range(0.0))
    min_valid_fraction: float = _opt(0.1, "a two-view step needs this share of its matches triangulated (in front "
                                           "of both cameras, at min_angle_rad or more); under it the pose is "
                                           "taken as wrong and the frame is solved by PnP / rotation",
                                     range=_Range(0.0, 1.0))
    epipolar_correction: bool = _opt(False, "move each match onto its epipolar line before triangulating (the "
                                            "noise across the line is not parallax)")
    min_local_angle_rad: float = _opt(0.0, "drop triangulated points whose image cell sees the scene at a median "
                                           "ray angle under this (radians; 0 = off)", range=_Range(0.0))
    local_angle_keep: float = _opt(0.75, "the cell floor is lowered so that a step keeps at least this share of "
                                         "its points", range=_Range(0.0, 1.0))
    local_angle_cell_px: float = _opt(32.0, "side of the image cells of min_local_angle_rad, in pixels",
                                      range=_Range(1.0))
    pnp_reproj_px: float = _opt(1.0, "PnP RANSAC reprojection threshold in pixels", range=_Range(0.0, lo_open=True))
    pnp_min_inlier_ratio: float = _opt(0.1, "a PnP against a held keyframe with a smaller share of its points as "
                                            "inliers means the flow against the keyframe was lost: the frame is "
                                            "solved again through the previous frame", range=_Range(0.0, 1.0))


@dataclass(frozen=True)
class ScaleConfig(_Section):
    """Scale of the two-view translation against the keyframe depth."""

    NAME = "scale"
    source: Literal["auto", "triangulation", "keyframe-depth", "depth"] = _opt(
        "auto", "where the step length comes from: triangulation = depth carried from earlier triangulation; "
                "keyframe-depth = the depth network's prediction of the keyframe, frame to keyframe; depth = the "
                "authors' recipe, every pair fitted to the network depth of the new frame; auto = keyframe-depth "
                "with depth.model, else triangulation")
    min_points: int = _opt(20, "fewest triangulated points with reference depth to align the scale",
                           range=_Range(3))
    depth_min_flow_px: float = _opt(5.0, "scale.source=depth: mean flow in pixels under which PnP on the "
                                         "previous frame's depth is used instead of two-view", range=_Range(0.0))
    depth_fit_threshold: float = _opt(1.0, "scale.source=depth: RANSAC residual (depth units) of the scale fit "
                                           "of network depth to triangulated depth", range=_Range(0.0, lo_open=True))
    depth_fit_trials: int = _opt(100, "scale.source=depth: RANSAC trials of the scale fit", range=_Range(1))
    depth_fit_min_points: int = _opt(100, "scale.source=depth: fewest points for the scale fit (else PnP)",
                                     range=_Range(3))
    depth_max: float = _opt(50.0, "scale.source=depth: PnP uses the previous frame's depth below this",
                            range=_Range(0.0, lo_open=True))
    pnp_check_ratio: float = _opt(1.5, "PnP replaces the two-view step when their scales differ by more than "
                                       "this factor; 0 = no check", check=_ratio_or_off, rule="0 (off) or > 1")
    pnp_check_ratio_low: float = _opt(1.15, "the same check's factor for a two-view step on a median parallax "
                                            "(rotation removed) under pnp_check_low_parallax_px, where the step's "
                                            "own scale is the less reliable one; 0 = such steps are not checked",
                                      check=_ratio_or_off, rule="0 (off) or > 1")
    pnp_check_low_parallax_px: float = _opt(8.0, "median parallax in pixels under which pnp_check_ratio_low applies; "
                                                 "0 = pnp_check_ratio for every step", range=_Range(0.0))


@dataclass(frozen=True)
class KeyframeConfig(_Section):
    """When the camera counts as static and when a new keyframe is made."""

    NAME = "keyframes"
    static_flow_px: float = _opt(0.25, "median flow in pixels under which the camera is taken as static",
                                 range=_Range(0.0))
    policy: Literal["gric", "parallax"] = _opt(
        "gric", "when a frame pair is solved by two-view geometry (and the frame becomes a keyframe): gric = "
                "general motion must beat rotation-only by GRIC and fix the translation direction to "
                "max_direction_deg; parallax = median parallax of at least min_parallax_px")
    min_parallax_px: float = _opt(3.0, "policy parallax: median parallax in pixels (rotation removed) needed for a "
                                       "new keyframe", range=_Range(0.0, 100.0))
    max_direction_deg: float = _opt(0.5, "policy gric: largest standard deviation of the translation direction "
                                         "(degrees) for a two-view step; above it PnP on the keyframe's depth",
                                    range=_Range(0.0, lo_open=True))
    init_min_parallax_px: float = _opt(1.0, "policy gric: median parallax in pixels (rotation removed) a two-view "
                                            "step needs while the keyframe has no depth (it sets the unit of scale "
                                            "and the first depth); under it rotation only; 0 = off",
                                       range=_Range(0.0, 100.0))
    depth_min_parallax_deg: float = _opt(0.2, "policy gric: median parallax (rotation removed) as an angle in degrees "
                                              "(pixels over the mean focal length) a two-view step needs while the "
                                              "keyframe has depth; under it PnP on that depth (a short baseline's "
                                              "rotation error tilts the new depth); 0 = off",
                                         range=_Range(0.0, 10.0))
    min_inlier_share: float = _opt(0.5, "policy gric: a PnP frame whose inlier ratio falls under this share of the "
                                        "first PnP frame's on the same held keyframe becomes the keyframe (its "
                                        "depth moved by the solved pose): the keyframe's points are fading; "
                                        "0 = off", range=_Range(0.0, 1.0))
    handon_min_angle_deg: float = _opt(3.0, "policy gric: when a PnP frame becomes the keyframe, its matches to the "
                                            "held keyframe that carry no depth are triangulated along the PnP pose, "
                                            "scaled by the matches that do, and join the handed-on depth where their "
                                            "rays meet at this angle (degrees) or more: the depth follows the view "
                                            "into new parts of the scene; 0 = only the carried depth is handed on. "
                                            "Lower angles add more points and pull the scale down (7-Scenes: README)",
                                       range=_Range(0.0, 90.0))
    max_flow_fraction: float = _opt(0.1, "policy gric: a PnP / rotation-only frame whose mean flow against the "
                                          "held keyframe exceeds this fraction of the image width becomes the "
                                          "keyframe (its depth moved by the solved pose)",
                                    range=_Range(0.0, lo_open=True))
    max_next_flow_fraction: float = _opt(0.125, "policy gric: a PnP / rotation-only frame also becomes the "
                                                 "keyframe when the flow against the held keyframe expected at the "
                                                 "next frame (this one's times (n+1)/n after n frames held) exceeds "
                                                 "this fraction of the image width, the range DIS can follow",
                                         range=_Range(0.0, lo_open=True))
    noise_floor_px: float = _opt(0.1, "policy gric: smallest flow noise assumed (pixels) when the matches' "
                                      "residuals say less", range=_Range(0.0, lo_open=True))
    independent_matches: int = _opt(500, "policy gric: matches counted as independent when propagating the noise "
                                         "to the direction (dense flow errors are correlated)", range=_Range(8))


@dataclass(frozen=True)
class BackendConfig(_Section):
    """What revises poses after each new keyframe."""

    NAME = "backend"
    # add a back-end by adding its name to this Literal
    kind: Literal["window-ba", "none"] = _opt(
        "window-ba", "back-end run on each new keyframe: window-ba = sliding-window bundle adjustment (GTSAM); "
                     "none = front-end poses only")
    window: int = _opt(6, "keyframes in the bundle-adjustment window; 0 = no back-end (the paper's pure "
                          "two-view pipeline)", check=lambda v: None if v == 0 or 3 <= v <= 100 else
                       f"{_show(v)} is out of range; must be 0 (off) or in [3, 100]", rule="0 or [3, 100]")
    fixed: int = _opt(2, "oldest keyframes of the window held fixed (they hold the gauge; two also the scale)",
                      range=_Range(1, 99))
    huber_px: float = _opt(1.0, "Huber threshold of the reprojection errors, pixels", range=_Range(0.0, lo_open=True))
    max_iterations: int = _opt(5, "Levenberg-Marquardt iterations per window at most", range=_Range(1, 1000))
    every: int = _opt(2, "adjust the window on every n-th keyframe (tracks follow every keyframe)",
                      range=_Range(1, 100))
    max_tracks: int = _opt(250, "most tracks alive at once", range=_Range(10, 100000))
    cell_px: int = _opt(32, "grid cell (pixels) over which new tracks are spread, one per cell",
                        range=_Range(2, 1024))
    track_texture_px: int = _opt(9, "a new track starts at the match of its grid cell with the most texture: the "
                                    "smaller eigenvalue of the image gradients' covariance over a block of this "
                                    "many pixels (about DIS's patch); 0 = the first match drawn",
                                 range=_Range(0, 31))
    track_fb_px: float = _opt(1.0, "a track ends where the flow's forward-backward distance reaches this (pixels)",
                              range=_Range(0.0, lo_open=True))
    track_epi_px: float = _opt(1.0, "a track ends where its new pixel is this far (Sampson, pixels) from the "
                                    "step's epipolar geometry", range=_Range(0.0, lo_open=True))
    outlier_px: float = _opt(3.0, "a track ends when its reprojection error after the adjustment exceeds this "
                                  "(pixels)", range=_Range(0.0, lo_open=True))
    min_points: int = _opt(30, "fewest points for an adjustment (and for a depth rescale)", range=_Range(3))
    step_factors: bool = _opt(True, "add the front-end's relative pose of each keyframe step as a factor")
    step_rot_deg: float = _opt(0.05, "sigma of a step factor's rotation, degrees", range=_Range(0.0, lo_open=True))
    step_trans: float = _opt(0.02, "sigma of a step factor's translation, as a fraction of the step length",
                             range=_Range(0.0, lo_open=True))
    step_trans_pnp: float = _opt(1.0, "sigma of the translation of a step solved by PnP or rotation only (a "
                                      "handed-on keyframe), as a fraction of the window's median two-view step "
                                      "(or of its own length when larger)", range=_Range(0.0, lo_open=True))
    depth_correction: Literal["none", "affine", "shape", "scale"] = _opt(
        "shape", "correct the carried depth of the keyframe after an adjustment to the adjusted points seen in it: "
                 "shape = an affine map of inverse depth (a two-view step's small rotation error shifts all "
                 "inverse depths alike) with the median depth kept (the front-end's scale), affine = the same "
                 "map with its scale, scale = one factor, none = keep the front-end's depth (measured, seeds "
                 "0-11: shape better than none on KITTI 07 and, with 6000 matches, on 7-Scenes stride 3; affine "
                 "worse on the unseen clips; README, back-end)")
    depth_correction_max: float = _opt(1.5, "an affine depth correction is refused for a scale-only one (shape: for "
                                            "none) when it would change the depth of the keyframe's tracks (2nd to "
                                            "98th percentile) by factors differing by more than this (larger ones "
                                            "rest on the few far points of a near scene)",
                                       range=_Range(1.0, lo_open=True))
    depth_correction_t: float = _opt(4.24, "an affine or shape correction's offset of inverse depth is kept only "
                                           "when it lies at least this many standard errors from zero (its fit's "
                                           "residuals); else affine falls back to a rescale and shape makes none; "
                                           "0 = off. The standard error falls with the square root of the points "
                                           "the fit finds front-end depth for, which grow with sampling.n_samples: "
                                           "3 was measured at 6000 matches, 3 x sqrt(2) = 4.24 keeps that bar at "
                                           "12000 (README, back-end)", range=_Range(0.0))
    depth_correction_min: float = _opt(0.1, "a depth correction is not applied when it would change no depth of the "
                                            "keyframe's tracks (2nd, 50th, 98th percentile) by more than this "
                                            "fraction (smaller ones are mostly the fit's noise; measured: README, "
                                            "back-end)", range=_Range(0.0))
    concurrent: bool = _opt(True, "adjust each window in a worker process while the next frames are solved; "
                                  "the revision is applied at the next keyframe (the same final poses, less time "
                                  "per frame)")
    max_shift: float = _opt(0.5, "an adjustment moving a keyframe by more than this many keyframe steps is "
                                 "rejected", range=_Range(0.0, lo_open=True))
    max_rotation_deg: float = _opt(3.0, "an adjustment rotating a keyframe by more than this (degrees) is rejected",
                                   range=_Range(0.0, lo_open=True))
    anchors: int = _opt(2, "old keyframes (out of the window) that see what the newest keyframe sees may join a "
                           "window as held poses, their points linked into the newest keyframe through a dense "
                           "flow; at most this many per window; 0 = off", range=_Range(0, 10))
    anchor_keep: int = _opt(48, "old keyframes kept as possible anchors (their images at working resolution; when "
                                "full, the one nearest another is dropped)", range=_Range(1, 1000))
    anchor_revisit_ratio: float = _opt(1.0, "an old keyframe is revisited when the newest keyframe's centre is "
                                            "nearer to it than this x the path travelled since; 1 = any old "
                                            "keyframe in view, no return needed", range=_Range(0.0, 1.0, lo_open=True))
    anchor_max_angle_deg: float = _opt(30.0, "largest angle between the optical axes of an anchor and the newest "
                                             "keyframe (degrees)", range=_Range(0.0, 180.0, lo_open=True))
    anchor_min_links: int = _opt(40, "fewest points linked from an anchor into the newest keyframe for it to join",
                                 range=_Range(8))
    anchor_max_parallax_px: float = _opt(100.0, "an old keyframe joins only when its points, turned to the newest "
                                               "keyframe's orientation, are this near (median, pixels) to where "
                                               "they project: what the flow can find", range=_Range(0.0, lo_open=True))
    anchor_max_zoom: float = _opt(1.25, "an old keyframe joins only when its points' depths in the two views "
                                        "differ by at most this factor (median; the flow does not link a view "
                                        "much nearer or farther: on KITTI no try above 2 linked)",
                                  range=_Range(1.0))
    anchor_max_shared: int = _opt(40, "an old keyframe with at least this many of its points still tracked into "
                                      "the newest keyframe is not tried: the window's tracks already link the "
                                      "two (on KITTI every try was such a keyframe, and none changed the poses)",
                                  range=_Range(1))
    anchor_gate_px: float = _opt(20.0, "a linked pixel farther than this from where the current pose projects "
                                       "the anchor's point is dropped (pixels)", range=_Range(0.0, lo_open=True))

    def _check_together(self, source: str) -> None:
        if self.window and self.fixed >= self.window:
            raise ConfigError(f"{self.fixed} must be smaller than backend.window ({self.window})", source,
                              "backend.fixed")


@dataclass(frozen=True)
class OutputConfig(_Section):
    """What the run writes besides the trajectory."""

    NAME = "output"
    gt: Path | None = _opt(None, "ground-truth trajectory to evaluate against; null = none")
    plot: bool = _opt(True, "write trajectory plots")
    rerun: Path | None = _opt(None, "write a Rerun recording (.rrd) here; null = none")
    rerun_spawn: bool = _opt(False, "open the Rerun viewer live while running")


@dataclass(frozen=True)
class RuntimeConfig(_Section):
    """Compute resources."""

    NAME = "runtime"
    threads: int = _opt(2, "CPU threads for OpenCV and the ONNX runtime", range=_Range(1, 64))
    blas_threads: int = _opt(1, "threads of NumPy's BLAS during a run (main process and back-end worker); its "
                             "products are small, and more threads spin-wait on the cores the flow thread and "
                             "the back-end need (KITTI 00 on 2 cores: 12.6 frames/s with 1 against 8.8 with 2, "
                             "same poses)", range=_Range(1, 64))


class ConfigRoot:
    """Base of a configuration tree: a frozen dataclass whose fields are sections (:class:`_Section`).

    :class:`Config` (a run) is one; the training command has its own
    (:class:`trianflow_vo.train.config.TrainConfig`). Files, presets, ``--set`` and the YAML
    writer work on any root.
    """

    def __post_init__(self) -> None:
        hints = _hints(type(self))
        for f in dataclasses.fields(self):  # type: ignore[arg-type]
            cls = hints[f.name]
            v = getattr(self, f.name)
            if not isinstance(v, cls):
                raise ConfigError(f"section '{f.name}' must be a {cls.__name__}, got {type(v).__name__}",
                                  type(self).__name__)

    def to_dict(self) -> dict:
        """Nested plain dict (Path -> str, tuple -> list), JSON/YAML-ready, sections in order."""
        return {s.name: {f.name: _plain(getattr(getattr(self, s.name), f.name))
                         for f in dataclasses.fields(getattr(self, s.name))}
                for s in dataclasses.fields(self)}  # type: ignore[arg-type]


@dataclass(frozen=True)
class Config(ConfigRoot):
    """The whole configuration of a run; ``Config()`` is the defaults."""

    input: InputConfig = field(default_factory=InputConfig)
    flow: FlowConfig = field(default_factory=FlowConfig)
    depth: DepthConfig = field(default_factory=DepthConfig)
    sampling: SamplingConfig = field(default_factory=SamplingConfig)
    geometry: GeometryConfig = field(default_factory=GeometryConfig)
    scale: ScaleConfig = field(default_factory=ScaleConfig)
    keyframes: KeyframeConfig = field(default_factory=KeyframeConfig)
    backend: BackendConfig = field(default_factory=BackendConfig)
    output: OutputConfig = field(default_factory=OutputConfig)
    runtime: RuntimeConfig = field(default_factory=RuntimeConfig)


# -- checking values --------------------------------------------------------------------------------------------
_HINTS: dict[type, dict[str, Any]] = {}
_FLOAT_NO_DOT = re.compile(r"[-+]?[0-9]+[eE][-+]?[0-9]+")  # '1e-3': a string to YAML 1.1, a float to us


def _hints(cls: type) -> dict[str, Any]:
    if cls not in _HINTS:
        _HINTS[cls] = typing.get_type_hints(cls)
    return _HINTS[cls]


def _num(v: float) -> str:
    return str(int(v)) if float(v).is_integer() else repr(float(v))


def _show(v: Any) -> str:
    """A value as a user wrote it: strings quoted, paths as strings, None as null."""
    if v is None:
        return "null"
    if isinstance(v, bool):
        return "true" if v else "false"
    if isinstance(v, os.PathLike):
        return repr(os.fspath(v))
    if isinstance(v, (list, tuple)):
        return "[" + ", ".join(_show(x) for x in v) + "]"
    return repr(v)


def _plain(v: Any) -> Any:
    if isinstance(v, Path):
        return str(v)
    if isinstance(v, tuple):
        return [_plain(x) for x in v]
    return v


def _split_optional(hint: Any) -> tuple[Any, bool]:
    if typing.get_origin(hint) in (Union, types.UnionType):
        args = [a for a in typing.get_args(hint) if a is not type(None)]
        if len(args) != 1:
            raise TypeError(f"unsupported config type {hint!r}")
        return args[0], True
    return hint, False


class _Bad(Exception):
    """A value that does not fit (message without source or key)."""


def _as_int(v: Any) -> int:
    if isinstance(v, bool) or not isinstance(v, numbers.Integral):
        raise _Bad(f"{_show(v)} is not an integer")
    return int(v)


def _as_float(v: Any) -> float:
    if isinstance(v, str) and _FLOAT_NO_DOT.fullmatch(v.strip()):
        v = float(v)
    if isinstance(v, bool) or not isinstance(v, numbers.Real):
        raise _Bad(f"{_show(v)} is not a number")
    f = float(v)
    if not math.isfinite(f):
        raise _Bad(f"{_show(v)} is not a finite number")
    return f


def _coerce(hint: Any, meta: Mapping[str, Any], v: Any) -> Any:
    base, optional = _split_optional(hint)
    if v is None:
        if optional:
            return None
        raise _Bad(f"null is not allowed; expected {_type_text(hint, meta)}")
    origin = typing.get_origin(base)
    if origin is Literal:
        choices = typing.get_args(base)
        if isinstance(v, str) and v in choices:
            return v
        raise _Bad(f"{_show(v)} is not one of {', '.join(choices)}")
    if base is bool:
        if isinstance(v, bool):
            return v
        raise _Bad(f"{_show(v)} is not a bool (true or false)")
    if base is int:
        return _as_int(v)
    if base is float:
        return _as_float(v)
    if base is str:
        if isinstance(v, str):
            return v
        raise _Bad(f"{_show(v)} is not a string")
    if base is Path:
        if isinstance(v, (str, os.PathLike)) and not isinstance(v, bytes):
            if os.fspath(v) == "":
                raise _Bad("'' is not a path (use null for none)")
            return v if type(v) is type(Path()) else Path(v)
        raise _Bad(f"{_show(v)} is not a path")
    if origin is tuple and typing.get_args(base)[1:] == (Ellipsis,):  # tuple[T, ...]: any length
        item = typing.get_args(base)[0]
        sep = meta.get("sep")
        raw = v
        if isinstance(v, str):
            v = [] if not v.strip() else [s.strip() for s in v.split(sep or ",")]
        if not isinstance(v, (list, tuple)):
            raise _Bad(f"{_show(raw)} is not {meta.get('form') or 'a list'}")
        return tuple(_coerce(item, {}, x) for x in v)
    if origin is tuple:
        items = typing.get_args(base)
        form = meta.get("form") or f"a list of {len(items)}"
        sep = meta.get("sep")
        raw = v
        if isinstance(v, str) and sep:
            parts = re.split(re.escape(sep), v.strip(), flags=re.IGNORECASE)
            try:
                v = [int(p) if items[0] is int else float(p) for p in parts]
            except ValueError:
                raise _Bad(f"{_show(raw)} is not {form}") from None
        if not isinstance(v, (list, tuple)) or len(v) != len(items):
            raise _Bad(f"{_show(raw)} is not {form}")
        try:
            out = tuple(_coerce(t, {}, x) for t, x in zip(items, v))
        except _Bad:
            raise _Bad(f"{_show(raw)} is not {form}") from None
        return out
    raise TypeError(f"unsupported config type {hint!r}")


def _check_value(hint: Any, meta: Mapping[str, Any], v: Any, source: str, key: str) -> Any:
    """``v`` normalised to the field's type, or ConfigError naming ``source`` and ``key``."""
    try:
        out = _coerce(hint, meta, v)
        if out is not None:
            rng, check = meta.get("range"), meta.get("check")
            if rng is not None and out not in rng:
                raise _Bad(rng.error(v))
            if check is not None:
                msg = check(out)
                if msg:
                    raise _Bad(msg)
    except _Bad as e:
        raise ConfigError(str(e), source, key) from None
    return out


def _type_text(hint: Any, meta: Mapping[str, Any]) -> str:
    base, optional = _split_optional(hint)
    origin = typing.get_origin(base)
    if origin is Literal:
        text = "one of " + ", ".join(typing.get_args(base))
    elif origin is tuple:
        text = meta.get("form") or "list"
    else:
        text = {bool: "bool", int: "int", float: "float", str: "str", Path: "path"}[base]
    rng = meta.get("range")
    if rng is not None:
        rule = rng.text()
        text += (" in " if rule[0] in "[(" else " ") + rule
    elif meta.get("rule"):
        rule = meta["rule"]
        text += ((" " if rule[0] in "<>" else ": ") if origin is None else ", ") + rule
    if optional:
        text += ", or null" if "," in text or " " in text else " or null"
    return text


# -- building ---------------------------------------------------------------------------------------------------
def _section_classes(root: type = None) -> dict[str, type]:
    return dict(_hints(root or Config))


def merge_dict(config: Config, data: Mapping, source: str) -> Config:
    """``config`` with the partial nested dict ``data`` (``{section: {key: value}}``) applied on top.

    A section given as null (all its keys commented out in YAML) changes nothing.
    Raises ConfigError naming ``source`` on an unknown section or key or a bad value.
    """
    sections = _section_classes(type(config))
    if not isinstance(data, Mapping):
        raise ConfigError(f"the configuration must be a mapping of sections ({', '.join(sections)}), "
                          f"got {_type_name(data)}", source)
    new: dict[str, Any] = {}
    for name, values in data.items():
        if name not in sections:
            raise ConfigError(f"unknown section {_show(name)}; valid sections: {', '.join(sections)}", source)
        if values is None:
            continue
        if not isinstance(values, Mapping):
            raise ConfigError(f"section '{name}' must be a mapping of keys, got {_type_name(values)}", source)
        current = new.get(name, getattr(config, name))
        keys = [f.name for f in dataclasses.fields(current)]
        for key in values:
            if key not in keys:
                raise ConfigError(f"unknown key '{name}.{key}'; valid keys of {name}: {', '.join(sorted(keys))}",
                                  source)
        try:
            new[name] = dataclasses.replace(current, **values)
        except ConfigError as e:
            raise ConfigError(e.message, source, e.key) from None
    return dataclasses.replace(config, **new) if new else config


def config_from_dict(data: Mapping, source: str = "<dict>", root: type = None) -> Config:
    """A Config (or another ``root``) from a partial nested dict (missing sections and keys keep their defaults)."""
    return merge_dict((root or Config)(), data, source)


def apply_overrides(config: Config, overrides: Sequence[str], source: str = "--set") -> Config:
    """``config`` with each ``section.key=value`` applied in order; values are parsed as YAML.

    So ``3``, ``0.5``, ``true``, ``null`` (or nothing after ``=``), ``[256, 832]``, ``fine``.
    """
    import yaml

    if isinstance(overrides, str):
        overrides = [overrides]
    for item in overrides:
        text = item if isinstance(item, str) else repr(item)
        left, eq, right = text.partition("=")
        dotted = left.strip()
        section, dot, key = dotted.partition(".")
        if not eq or not dot or not section or not key:
            raise ConfigError(f"{text!r} is not section.key=value (e.g. sampling.seed=3)", source)
        try:
            value = yaml.safe_load(right)
        except yaml.YAMLError as e:
            problem = getattr(e, "problem", None) or str(e).splitlines()[0]
            raise ConfigError(f"cannot read value {right!r} as YAML: {problem}", source, dotted) from None
        config = merge_dict(config, {section: {key: value}}, source)
    return config


def _type_name(v: Any) -> str:
    return {list: "a list", str: "a string", int: "an integer", float: "a number", bool: "a bool",
            type(None): "null"}.get(type(v), type(v).__name__)


# -- files and presets ------------------------------------------------------------------------------------------
def _one_line(text: str) -> str:
    return " ".join(str(text).split())


def _parse_yaml(text: str, source: str) -> Any:
    import yaml

    try:
        return yaml.safe_load(text)
    except yaml.MarkedYAMLError as e:
        mark = e.problem_mark or e.context_mark
        what = _one_line(e.problem or e.context or "syntax error")
        col = f" (column {mark.column + 1})" if mark is not None else ""
        raise ConfigError(f"invalid YAML: {what}{col}", source, line=None if mark is None else mark.line + 1) \
            from None
    except yaml.YAMLError as e:
        raise ConfigError(f"invalid YAML: {_one_line(e)}", source) from None


def _parse_json(text: str, source: str) -> Any:
    import json

    try:
        doc = json.loads(text)
    except json.JSONDecodeError as e:
        raise ConfigError(f"invalid JSON: {e.msg} (column {e.colno})", source, line=e.lineno) from None
    if isinstance(doc, dict) and "config" in doc:  # a run.json: the configuration is under "config"
        doc = doc["config"]
        if not isinstance(doc, Mapping):
            raise ConfigError(f"'config' must be a mapping of sections, got {_type_name(doc)}", source)
    return doc


def _from_document(doc: Any, source: str, root: type = None, base=None) -> Config:
    if doc is None:  # an empty file (or only comments): the defaults
        doc = {}
    if not isinstance(doc, Mapping):
        raise ConfigError(f"the document must be a mapping of sections ({', '.join(_section_classes(root))}), "
                          f"got {_type_name(doc)}", source)
    return merge_dict(base if base is not None else (root or Config)(), doc, source)


def _load_file(path: Path, root: type = None, base=None) -> Config:
    source = str(path)
    try:
        text = path.read_text(encoding="utf-8")
    except UnicodeDecodeError:
        raise ConfigError("not a text file (UTF-8)", source) from None
    except OSError as e:
        raise ConfigError(f"cannot read: {e.strerror or e}", source) from None
    doc = _parse_json(text, source) if path.suffix.lower() == ".json" else _parse_yaml(text, source)
    return _from_document(doc, source, root, base)


def _presets(package: str = PRESET_PACKAGE):
    from importlib.resources import files

    return files(package)


def preset_names(package: str = PRESET_PACKAGE) -> list[str]:
    """Names of the presets shipped in ``package`` (for runs: ``default``, ``indoor``, ``kitti``), sorted."""
    return sorted(e.name[:-5] for e in _presets(package).iterdir() if e.name.endswith(".yaml"))


def load_config(path_or_name: str | Path, *, root: type = None, package: str = PRESET_PACKAGE,
                base=None) -> Config:
    """A Config from a ``.yaml``/``.yml`` file, a ``.json`` file (a run.json's ``"config"``
    mapping, or the whole document) or a shipped preset name (``default``, ``kitti``,
    ``indoor``) that is not an existing file. Keys a file leaves out keep their defaults
    (or the values of ``base``, a config of the same ``root``, when given).

    ``root`` (default :class:`Config`) and ``package`` (where its presets live) let another
    configuration tree (the training command's) use the same files, presets and errors.
    """
    p = Path(path_or_name)
    if p.is_file():
        return _load_file(p, root, base)
    name = os.fspath(path_or_name)
    names = preset_names(package)
    if name in names:
        source = f"preset '{name}'"
        doc = _parse_yaml((_presets(package) / f"{name}.yaml").read_text(encoding="utf-8"), source)
        return _from_document(doc, source, root, base)
    if p.is_dir():
        raise ConfigError("is a directory, not a configuration file", name)
    if not p.suffix and os.sep not in name and "/" not in name:
        raise ConfigError(f"no such file or preset; presets: {', '.join(names)}", name)
    raise ConfigError("no such file", name)


def _yaml_value(v: Any) -> str:
    """One value as a YAML flow scalar or flow list, e.g. ``0.25``, ``null``, ``[256, 832]``."""
    import yaml

    text = yaml.safe_dump(_plain(v), default_flow_style=True, width=10**6)
    return text.removesuffix("\n").removesuffix("\n...").strip()


def _render_yaml(config: Config, header: Sequence[str] = (), comments: bool = True) -> str:
    """YAML text of every key of ``config``, grouped by section, with each key's help as a comment."""
    lines = [f"# {h}" if h and not h.startswith("#") else h for h in header]
    for s in dataclasses.fields(config):
        section = getattr(config, s.name)
        if lines:
            lines.append("")
        if comments and type(section).__doc__:
            lines.append(f"# {type(section).__doc__.strip().splitlines()[0]}")
        lines.append(f"{s.name}:")
        rows = [(f"  {f.name}: {_yaml_value(getattr(section, f.name))}", f.metadata["help"])
                for f in dataclasses.fields(section)]
        width = max(len(r[0]) for r in rows)
        for text, help in rows:
            lines.append(f"{text.ljust(width)}  # {help}" if comments else text)
    return "\n".join(lines) + "\n"


def write_config_yaml(config: Config, path: Path, header: str = HEADER) -> None:
    """Write the full effective ``config`` as YAML that :func:`load_config` reads back equal."""
    Path(path).write_text(_render_yaml(config, [header]), encoding="utf-8")


# -- docs -------------------------------------------------------------------------------------------------------
def config_keys(root: type = None) -> list[tuple[str, str, object, str]]:
    """``(dotted key, type text, default, help)`` of every field, in section and field order."""
    out = []
    for s, cls in _section_classes(root).items():
        hints = _hints(cls)
        for f in dataclasses.fields(cls):
            out.append((f"{s}.{f.name}", _type_text(hints[f.name], f.metadata), f.default, f.metadata["help"]))
    return out


def _keys_markdown(root: type = None) -> str:
    """The Markdown table of :func:`config_keys` (configs/README.md embeds it)."""
    def cell(text: str) -> str:
        return text.replace("|", "\\|")

    rows = [f"| `{k}` | {cell(t)} | `{_yaml_value(d)}` | {cell(h)} |" for k, t, d, h in config_keys(root)]
    return "\n".join(["| key | type | default | help |", "|---|---|---|---|", *rows]) + "\n"


def resolve_scale_source(config: Config) -> str:
    """``scale.source`` with ``auto`` resolved: ``keyframe-depth`` when a depth network is given, else
    ``triangulation``. Raises ConfigError when a depth-based source has no ``depth.model``."""
    src = config.scale.source
    if src == "auto":
        return "keyframe-depth" if config.depth.model is not None else "triangulation"
    if src in ("keyframe-depth", "depth") and config.depth.model is None:
        raise ConfigError(f"scale.source: {src!r} needs a depth network (depth.model, --depth-model)")
    return src
