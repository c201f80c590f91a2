"""Typed processing settings from session.toml, validated once.

Defaults reproduce the original rig: a 256 mm cube whose min corner is the world
origin, carved at 2 mm (128^3 voxels), a fixed grey threshold of 60 on a dark
manipulator mounted at (128, 128, 0) mm.
"""

from __future__ import annotations

import json
import logging
import math
from dataclasses import dataclass, field, fields
from datetime import UTC, date, datetime, time, timedelta
from pathlib import Path
from typing import Any

from ..errors import SettingsError
from .toml_file import check_keys, read_toml

log = logging.getLogger(__name__)

SILHOUETTE_METHODS = ("threshold", "otsu", "background")
POLARITIES = ("dark", "bright")
CURVE_METHODS = ("fit", "polyfit")
TIP_SHAPES = ("flat", "round", "auto")

# A grid is refused when its per-session tables would not fit comfortably in memory.
# A run holds more than the tables' estimate (WorkspaceSettings.estimated_bytes): with 2
# workers at 1 mm voxels (`make bench`, 2026-12-04), 1.39 GB at its peak against 0.42 GB
# estimated; during a run of a 0.38 mm grid, 7.6 GB estimated, the machine's memory in use
# peaked at 17 GB.
MAX_GRID_BYTES = 4 * 1024**3
# Tube radii a real rig can have. Below 0.1 mm is metres typed for millimetres (every
# frame then failed in OpenCV or asked for terabytes); above 100 mm no camera of the rig
# sees a whole tube.
RADIUS_RANGE_MM = (0.1, 100.0)
# Grey levels (or differences) that split an 8-bit image: 0 and 255 keep no pixel or
# every pixel, and a silhouette of the whole image made the outputs hundreds of MB.
THRESHOLD_RANGE = (1, 254)
# Frame times are ns since the Unix epoch in an int64 (MCAP log_time, Rerun's timeline).
EPOCH = datetime(1970, 1, 1, tzinfo=UTC)
LAST_TIMESTAMP = EPOCH + timedelta(microseconds=(2**63 - 1) // 1000)


@dataclass(frozen=True)
class Workspace:
    """The carving box: an axis-aligned cube split into cubic voxels (world frame, mm)."""

    origin_mm: tuple[float, float, float] = (0.0, 0.0, 0.0)
    size_mm: tuple[float, float, float] = (256.0, 256.0, 256.0)
    voxel_mm: float = 2.0

    @property
    def shape(self) -> tuple[int, int, int]:
        """Voxels along x, y, z."""
        nx, ny, nz = (max(1, round(s / self.voxel_mm)) for s in self.size_mm)
        return (nx, ny, nz)

    @property
    def voxel_count(self) -> int:
        nx, ny, nz = self.shape
        return nx * ny * nz

    def estimated_bytes(self, n_cameras: int) -> int:
        """Memory the per-session tables need: an int32 pixel index per voxel and camera,
        plus voxel centres (float32 x3) and a per-frame occupancy mask."""
        return self.voxel_count * (4 * n_cameras + 12 + 1)


@dataclass(frozen=True)
class SilhouetteSettings:
    method: str = "threshold"
    threshold: int = 60
    polarity: str = "dark"
    # Connected blobs smaller than this (px) cannot be the manipulator and are removed.
    min_area_px: int = 20


@dataclass(frozen=True)
class ManipulatorSettings:
    base_mm: tuple[float, float, float] | None = (128.0, 128.0, 0.0)
    radius_mm: float | None = 6.0
    # The tube's end: "flat" (cut square), "round" (a hemisphere, whose centre is the
    # backbone's end) or "auto" (chosen once per session from its frames).
    tip: str = "auto"


# The curve's samples, [centerline] points: the fit tracks, draws and judges the curve at
# them. On a tight loop (`synth --shape loop --frames 20 --seed 5`, `process`, `evaluate`;
# 2026-12-05) 16 gave 0.63 mm mean and the wrong tube end, 32 0.25 mm, 64 0.19 mm; on the
# default `synth --frames 20`, 1,024 cost 130 ms more a frame (one worker). More than
# the default 64 is no better: 128 on 124 rendered sessions (90 tracked frames each, same
# day) gave three-camera mean errors summed 10.62 -> 10.58 mm and 107 -> 114 frames more
# than 2 mm off, 23 sessions better and 18 worse by more than 0.005 mm, at the same CPU time.
CENTERLINE_POINTS = (32, 1024)


@dataclass(frozen=True)
class CenterlineSettings:
    method: str = "fit"
    points: int = 64
    # Temporal smoothing after the last frame (pipeline.run.smoothing), logged beside the
    # per-frame curves; on because it lowered every error on the synthetic shapes.
    smooth: bool = True


@dataclass(frozen=True)
class CalibrationSettings:
    # Cameras refined from the session's silhouettes (pipeline.calibrate.refine): "auto"
    # refines when the views disagree with the given cameras by more than their noise.
    refine: str | bool = "auto"


@dataclass(frozen=True)
class SessionInfo:
    # Frame i is at start_time + i / fps; the Unix epoch when session.toml does not say.
    start_time: datetime = datetime(1970, 1, 1, tzinfo=UTC)


@dataclass(frozen=True)
class LiveSettings:
    """``[live]``: camera name -> its source for ``pipeline live``, in the table's order.

    A source is a V4L2 device path (``/dev/video0``), a device index (``0``, read as
    ``/dev/video0``) or anything FFmpeg opens (``rtsp://``, ``udp://``, ``http://``,
    a named pipe); the table's integers are kept as their decimal text.
    """

    sources: tuple[tuple[str, str], ...] = ()

    def source(self, camera: str) -> str | None:
        return dict(self.sources).get(camera)


@dataclass(frozen=True)
class Settings:
    workspace: Workspace = field(default_factory=Workspace)
    silhouette: SilhouetteSettings = field(default_factory=SilhouetteSettings)
    manipulator: ManipulatorSettings = field(default_factory=ManipulatorSettings)
    centerline: CenterlineSettings = field(default_factory=CenterlineSettings)
    calibration: CalibrationSettings = field(default_factory=CalibrationSettings)
    session: SessionInfo = field(default_factory=SessionInfo)
    live: LiveSettings = field(default_factory=LiveSettings)


_SECTIONS: dict[str, type] = {
    "workspace": Workspace,
    "silhouette": SilhouetteSettings,
    "manipulator": ManipulatorSettings,
    "centerline": CenterlineSettings,
    "calibration": CalibrationSettings,
    "session": SessionInfo,
}


def describe(settings: Settings) -> str:
    """The settings that decide a reconstruction, on one line: the workspace box, the
    silhouette threshold, the manipulator's base, radius and tip."""
    ws, sil, man = settings.workspace, settings.silhouette, settings.manipulator
    base = "auto" if man.base_mm is None else f"({', '.join(f'{v:g}' for v in man.base_mm)}) mm"
    radius = "auto" if man.radius_mm is None else f"{man.radius_mm:g} mm"
    return (
        f"workspace {'x'.join(f'{v:g}' for v in ws.size_mm)} mm from "
        f"({', '.join(f'{v:g}' for v in ws.origin_mm)}), {ws.voxel_mm:g} mm voxels; "
        f"silhouette {sil.method} {sil.threshold}, {sil.polarity} tube; "
        f"base {base}, radius {radius}, tip {man.tip}"
    )


def load_settings(path: Path | None) -> Settings:
    """Read session.toml (None or a missing file gives the defaults) and validate it."""
    if path is None or not path.exists():
        return Settings()
    return settings_from_dict(read_toml(path, error=SettingsError), source=str(path))


def settings_from_dict(data: dict[str, Any], *, source: str = "session.toml") -> Settings:
    """Build validated :class:`Settings` from parsed TOML; raise SettingsError naming the key."""
    check_keys(data, {*_SECTIONS, "live"}, source, error=SettingsError, hint=_key_home)
    parts: dict[str, Any] = {"live": _live(data.get("live", {}), source)}
    for name, cls in _SECTIONS.items():
        section = data.get(name, {})
        if not isinstance(section, dict):
            raise SettingsError(f"{source}: [{name}] must be a table")
        allowed = {f.name: f for f in fields(cls)}
        check_keys(section, allowed, source, error=SettingsError, where=f"[{name}] ", hint=_key_home)
        parts[name] = cls(**{k: _convert(source, name, k, v) for k, v in section.items()})
    settings = Settings(**parts)
    _validate(settings, source)
    return settings


def _live(section: Any, source: str) -> LiveSettings:
    """``[live]``: camera name -> a source string, or a device index (a non-negative integer)."""
    if not isinstance(section, dict):
        raise SettingsError(f"{source}: [live] must be a table of camera name = source")
    pairs = []
    for camera, value in section.items():
        if isinstance(value, int) and not isinstance(value, bool) and value >= 0:
            value = str(value)
        if not isinstance(value, str) or not value.strip():
            raise SettingsError(
                f"{source}: [live] {camera} must be a device path, a device index or a stream URL "
                f'(e.g. "/dev/video0", 0, "udp://127.0.0.1:5000"), got {_short(value)}'
            )
        pairs.append((camera, value.strip()))
    return LiveSettings(tuple(pairs))


def _key_home(key: str) -> str:
    """The table an unknown ``key`` is a key of (a setting written above its table's header,
    or under another table), or "" (then the allowed name nearest its spelling is given)."""
    homes = [f"[{name}]" for name, cls in _SECTIONS.items() if key in {f.name for f in fields(cls)}]
    if len(homes) == 1:
        return f" (a key of {homes[0]}: put it under {homes[0]})"
    if homes:  # "method": a key of two tables
        return f" (a key of {' and '.join(homes)}: put it under one of them)"
    return ""


def _number(source: str, key: str, value: Any) -> float:
    try:
        # TOML integers are unbounded: float() overflows past ~1.8e308.
        number = float(value) if isinstance(value, int | float) and not isinstance(value, bool) else None
    except OverflowError:
        number = None
    if number is None or not math.isfinite(number):
        raise SettingsError(f"{source}: {key} must be a finite number, got {_short(value)}")
    return number


def _short(value: Any) -> str:
    """``value`` as TOML writes it, cut to one readable line (a fuzzed 300-digit integer is
    not): the user's file speaks TOML, not Python (true, not True; 2026-01-01, not
    datetime.date(2026, 1, 1))."""
    text = _as_toml(value)
    return text if len(text) <= 40 else text[:37] + "..."


def _as_toml(value: Any) -> str:
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, date | time):  # datetime is a date
        return value.isoformat()
    if isinstance(value, str):
        return json.dumps(value, ensure_ascii=False)
    if isinstance(value, list):
        return "[" + ", ".join(_as_toml(v) for v in value) + "]"
    if isinstance(value, dict):
        return "a table {" + ", ".join(f"{k} = {_as_toml(v)}" for k, v in value.items()) + "}"
    return repr(value)


def _vector3(source: str, key: str, value: Any) -> tuple[float, float, float]:
    if not isinstance(value, list) or len(value) != 3:
        raise SettingsError(f"{source}: {key} must be a list of 3 numbers, got {_short(value)}")
    x, y, z = (_number(source, key, v) for v in value)
    return (x, y, z)


def _convert(source: str, section: str, key: str, value: Any) -> Any:
    name = f"[{section}] {key}"
    if key in ("base_mm", "radius_mm") and value == "auto":
        return None  # inferred from the data (see centerline / quality)
    if key == "base_mm" and isinstance(value, str):
        raise SettingsError(f'{source}: {name} must be a list of 3 numbers or "auto", got {_short(value)}')
    if key == "radius_mm" and isinstance(value, str):
        raise SettingsError(f'{source}: {name} must be a number (mm) or "auto", got {_short(value)}')
    if key in ("origin_mm", "size_mm", "base_mm"):
        return _vector3(source, name, value)
    if key in ("voxel_mm", "radius_mm"):
        return _number(source, name, value)
    if key in ("threshold", "min_area_px", "points"):
        if isinstance(value, bool) or not isinstance(value, int):
            raise SettingsError(f"{source}: {name} must be an integer, got {_short(value)}")
        return value
    if key == "refine":
        if not (isinstance(value, bool) or value == "auto"):
            raise SettingsError(f'{source}: {name} must be "auto", true or false, got {_short(value)}')
        return value
    if key == "smooth":
        if not isinstance(value, bool):
            raise SettingsError(f"{source}: {name} must be true or false, got {_short(value)}")
        return value
    if key == "start_time":
        parsed = value if isinstance(value, datetime) else None
        if isinstance(value, str):
            try:
                parsed = datetime.fromisoformat(value)
            except ValueError:
                pass
        if parsed is not None:
            if parsed.tzinfo is None:
                # Hours off where the clock it was read from was not UTC's: said, not guessed.
                log.warning(
                    "%s: %s %s has no UTC offset; taken as UTC (add Z, or the offset: +01:00)",
                    source,
                    name,
                    parsed.isoformat(),
                )
                parsed = parsed.replace(tzinfo=UTC)
            return parsed
        raise SettingsError(f"{source}: {name} must be an RFC 3339 date-time, got {_short(value)}")
    if not isinstance(value, str):
        raise SettingsError(f"{source}: {name} must be a string, got {_short(value)}")
    return value


# How far outside the box the base may lie, in tube radii (the march from the base looks
# for the hull within about that); the radius assumed when session.toml gives none.
_BASE_SLACK_RADII = 3.0
_TYPICAL_RADIUS_MM = 6.0


def _check_base_in_workspace(s: Settings, source: str) -> None:
    """The base must lie in the carving box, or near enough for the centreline to find the
    hull from it: within three tube radii (a mount below a box that leaves the mount
    hardware out works; 15 mm below did, 40 mm did not). A base farther out leaves every
    frame without a curve, for a reason no frame could name."""
    base, ws = s.manipulator.base_mm, s.workspace
    if base is None:  # "auto": found from the data
        return
    slack = max(2.0 * ws.voxel_mm, _BASE_SLACK_RADII * (s.manipulator.radius_mm or _TYPICAL_RADIUS_MM))
    lo = [o - slack for o in ws.origin_mm]
    hi = [o + n + slack for o, n in zip(ws.origin_mm, ws.size_mm, strict=True)]
    if not all(a <= b <= c for a, b, c in zip(lo, base, hi, strict=True)):
        box = " x ".join(f"{o:g}..{o + n:g}" for o, n in zip(ws.origin_mm, ws.size_mm, strict=True))
        raise SettingsError(
            f"{source}: [manipulator] base_mm {_short(list(base))} is outside the workspace box "
            f"({box} mm); move base_mm or [workspace] origin_mm/size_mm so that the box holds the base"
        )


# A hull of voxels wider than this many tube radii is too coarse to follow the tube: on a
# rendered r 6 session (`pipeline synth`, 10 frames; 2026-12-04) 8 and 12 mm voxels gave
# the same curves as 2 mm ones (0.106 mm mean), 20 mm voxels failed 7 frames of 10 and
# 40 mm every frame; on `synth --frames 30` (r 6, 2026-12-05) 6, 9 and 12 mm voxels gave
# 0.101 mm and 14 mm failed 9 frames of 30 (too few voxels for a curve), and a tapered
# r 4.5 loop's 45 frames at 9 mm came within 0.153 mm (2 mm voxels: 0.159). Without a
# radius given, a grid needs MIN_VOXELS_ACROSS voxels across its narrowest side.
MAX_VOXEL_RADII = 2.0
MIN_VOXELS_ACROSS = 4


def _check_voxel_fits_the_tube(s: Settings, source: str) -> None:
    voxel, radius = s.workspace.voxel_mm, s.manipulator.radius_mm
    if radius is not None and voxel > MAX_VOXEL_RADII * radius:
        raise SettingsError(
            f"{source}: [workspace] voxel_mm {voxel:g} is more than {MAX_VOXEL_RADII:g} times the tube's "
            f"radius ([manipulator] radius_mm {radius:g}), too coarse to follow it; use at most "
            f"{MAX_VOXEL_RADII * radius:g}, or correct radius_mm if the tube is thicker"
        )
    narrowest = min(s.workspace.size_mm)
    if voxel * MIN_VOXELS_ACROSS > narrowest:
        raise SettingsError(
            f"{source}: [workspace] voxel_mm {voxel:g} leaves fewer than {MIN_VOXELS_ACROSS} voxels "
            f"across the workspace's {narrowest:g} mm; use at most {narrowest / MIN_VOXELS_ACROSS:g}"
        )


def _validate(s: Settings, source: str) -> None:
    ws = s.workspace
    if ws.voxel_mm <= 0:
        raise SettingsError(f"{source}: [workspace] voxel_mm must be > 0, got {ws.voxel_mm}")
    if min(ws.size_mm) <= 0:
        raise SettingsError(f"{source}: [workspace] size_mm must be > 0 on every axis")
    # Counted in floats first: a tiny voxel_mm (1e-320) makes the integer shape overflow.
    per_axis = [s / ws.voxel_mm for s in ws.size_mm]
    need = ws.estimated_bytes(3) if math.prod(per_axis) < 2**62 else math.inf
    if need > MAX_GRID_BYTES:
        # The voxel counts as the grid rounds them (Workspace.shape), where they are countable.
        nx, ny, nz = (f"{max(1, round(n))}" if n < 1e15 else f"{n:.3g}" for n in per_axis)
        raise SettingsError(
            f"{source}: a {nx}x{ny}x{nz} grid needs about {need / 1024**3:.1f} GiB "
            f"(limit {MAX_GRID_BYTES / 1024**3:.0f} GiB); raise voxel_mm or shrink size_mm"
        )
    sil = s.silhouette
    if sil.method not in SILHOUETTE_METHODS:
        raise SettingsError(
            f"{source}: [silhouette] method {sil.method!r} unknown; use one of "
            f"{', '.join(SILHOUETTE_METHODS)}"
        )
    if sil.polarity not in POLARITIES:
        raise SettingsError(
            f"{source}: [silhouette] polarity {sil.polarity!r} unknown; use one of {', '.join(POLARITIES)}"
        )
    lo, hi = THRESHOLD_RANGE
    if not lo <= sil.threshold <= hi:
        raise SettingsError(
            f"{source}: [silhouette] threshold must be in {lo}-{hi} (0 and 255 keep no pixel or "
            f"all of them), got {_short(sil.threshold)}"
        )
    if sil.min_area_px < 0:
        raise SettingsError(f"{source}: [silhouette] min_area_px must be >= 0")
    r = s.manipulator.radius_mm
    lo_mm, hi_mm = RADIUS_RANGE_MM
    if r is not None and not lo_mm <= r <= hi_mm:
        raise SettingsError(
            f"{source}: [manipulator] radius_mm must be in {lo_mm:g}-{hi_mm:g} (millimetres), got {r:g}"
        )
    _check_voxel_fits_the_tube(s, source)
    if s.manipulator.tip not in TIP_SHAPES:
        raise SettingsError(
            f"{source}: [manipulator] tip {s.manipulator.tip!r} unknown; use one of {', '.join(TIP_SHAPES)}"
        )
    start = s.session.start_time
    if not EPOCH <= start <= LAST_TIMESTAMP:
        raise SettingsError(
            f"{source}: [session] start_time {start.isoformat()} is outside 1970-01-01..2262-04-11, "
            "the range of a timestamp in nanoseconds since 1970; give a date in that range"
        )
    _check_base_in_workspace(s, source)
    if s.centerline.method not in CURVE_METHODS:
        raise SettingsError(
            f"{source}: [centerline] method {s.centerline.method!r} unknown; use one of "
            f"{', '.join(CURVE_METHODS)}"
        )
    low, high = CENTERLINE_POINTS
    if not low <= s.centerline.points <= high:
        raise SettingsError(
            f"{source}: [centerline] points must be in {low}-{high} (the curve's samples: fewer bend "
            "a coiled tube's curve off it, more slow every frame)"
        )
