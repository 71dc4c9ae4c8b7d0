"""``fr track``'s outputs, written as the frames are processed, and read back.

In the output folder (``--out``):

* ``frames.csv``: one record per processed frame (:data:`RECORD_KEYS`), appended and flushed as
  soon as the frame is fused, so that a stop loses no processed frame; with ``--json PATH`` the
  same records also go to PATH as JSON lines (``-``: standard output, for a pipe).  Nothing is
  kept in memory: the files grow, the process does not.
* ``calibration.json``: the fused calibration, the counters, the runs (*segments*) and the
  fusion's checkpoint (:meth:`fr_torch.video.fusion.OnlineCalibrator.checkpoint`), rewritten
  atomically (a temporary file renamed over it, :func:`fr_torch.output.write_text_atomic`: never
  seen half-written) when a run starts, whenever the fusion changes (a frame fused, held back or
  restarting it) and when the run ends.
* ``track.png``: drawn from the latest :data:`PLOT_RECORDS` records of ``frames.csv``
  (:func:`plot_records`), at the end of a run and on request.

**Resuming.**  A run whose ``--out`` already holds records of the same source appends to them
as a new *segment* (the ``segment`` column: 0 for the first run, then 1, 2, ...) and continues
the fusion from the checkpoint.  A file or folder continues after its last recorded frame (no
frame is recorded twice); a live source's new segment counts its frames from 0 again.  Records of
another source, or with other columns, are refused with one line; a last record cut short (a
killed process) is removed with one line.
"""
from __future__ import annotations

import csv
import io
import json
import math
import os
import sys
import time
from collections import deque
from dataclasses import dataclass
from datetime import datetime, timezone
from pathlib import Path
from typing import Any, Callable, TextIO

import numpy as np
import pandas as pd

from fr_torch.core.geometry.horizon import Horizon
from fr_torch.core.reliability.bounds import horizon_bound_pct
from fr_torch.errors import FRInputError
from fr_torch.output import dumps, output_folder, write_bytes_atomic, write_text_atomic
from fr_torch.redaction import redact_text
from fr_torch.runtime.schema import FLAT_COLUMNS, flat_record, horizon_unbounded, result_record
from fr_torch.video.fusion import FusedState
from fr_torch.video.sources import Frame, FrameStream, Source, log_line

RECORDS_FILE = "frames.csv"
CALIBRATION_FILE = "calibration.json"
FIGURE_FILE = "track.png"
#: Records the figure shows (the latest), and entries kept in calibration.json's lists.
PLOT_RECORDS = 5000
KEPT_ENTRIES = 100
#: Above this many records the figure shows dots without error bars (the bars would hide the track).
ERROR_BAR_RECORDS = 200

#: The track's own columns of a record, first.  ``segment``: the run that wrote it; ``frame``: the
#: frame's index (sources.Frame); ``time``: Unix time when the record was written (s); ``age_s``:
#: seconds from reading the frame off the source to writing its record; ``dropped``: live frames
#: dropped since the previous record; ``dropped_share``: share of this segment's frames dropped so
#: far; ``reconnects``: reconnections of the source in this segment; ``status``, ``epoch``,
#: ``restarted``, ``n_fused``, ``disagreement`` as FusedState; ``fused_*``: the fused calibration
#: after the frame (:func:`fused_calibration`; ``fused_sigma_*`` its standard deviations).
TRACK_KEYS = ("segment", "frame", "time", "age_s", "dropped", "dropped_share", "reconnects", "status", "epoch",
              "restarted", "fused_focal_px", "fused_roll_deg", "fused_tilt_deg", "fused_pan_deg",
              "fused_sigma_roll_deg", "fused_sigma_tilt_deg", "fused_sigma_focal_pct",
              "fused_horizon_left_y", "fused_horizon_right_y", "fused_horizon_bound_pct", "fused_horizon_unbounded",
              "n_fused", "disagreement")
#: Columns of frames.csv and keys of a JSON-lines record, in order: :data:`TRACK_KEYS`, then the
#: frame's estimate as every output writes it (:data:`fr_torch.runtime.schema.FLAT_COLUMNS`:
#: ``image`` is the frame's name).
RECORD_KEYS = TRACK_KEYS + FLAT_COLUMNS
#: Two-sided 90 % quantile of a standard normal: the fused horizon's bound from the fused sigmas.
Z90 = 1.6448536269514722

#: The first column of a fleet camera's records (its name).
CAMERA_KEY = "camera"

#: Statuses of a frame that change the fusion (calibration.json is rewritten after them).
CHANGES_FUSION = ("fused", "started", "restarted", "held")
ACCEPTED = ("fused", "started", "restarted")


def fused_calibration(state: FusedState) -> dict[str, Any] | None:
    """calibration.json's ``calibration``: the fused state (:meth:`FusedState.to_json`: frame,
    status, epoch, n_fused, focal_px, rotation, roll / tilt / pitch / pan in degrees, sigma,
    restarted, disagreement) with its ``hfov_deg``, ``principal_point`` ``[x, y]`` (pixels) and
    ``horizon`` ``{line, left_y, right_y, bound_pct, unbounded}`` as a frame's record has them, the
    bound from the fused standard deviations (90 %: :data:`Z90` sigma of the tilt and focal
    length; :func:`fr_torch.core.reliability.bounds.horizon_bound_pct`), null and ``unbounded``
    when it says nothing (:func:`fr_torch.runtime.schema.horizon_unbounded`).  None before the
    first accepted frame."""
    if not state.valid:
        return None
    sigma = state.sigma or {}
    bounds = None
    if sigma.get("tilt_deg") is not None and sigma.get("focal_pct") is not None:
        bounds = {"tilt_deg": Z90 * sigma["tilt_deg"], "focal_pct": Z90 * sigma["focal_pct"]}
    camera = state.camera
    bound = horizon_bound_pct(bounds, state.focal_px, state.tilt_deg, camera.height) if bounds else None
    horizon = Horizon.from_camera(camera, 0.0, bound)
    if horizon is not None:
        open_ = horizon_unbounded(bounds, state.tilt_deg, bound)
        horizon = dict(horizon.to_json(), bound_pct=None if open_ else bound, unbounded=open_)
    return dict(state.to_json(), hfov_deg=state.hfov_deg, principal_point=list(camera.principal_point),
                horizon=horizon)


def frame_record(frame: Frame, result, state: FusedState, segment: int, stream: FrameStream) -> dict[str, Any]:
    """The record of one processed frame (:data:`RECORD_KEYS`), timed now (``time``, ``age_s``)."""
    sigma = state.sigma or {}
    horizon = (fused_calibration(state) or {}).get("horizon") or {}
    return {"segment": segment, "frame": frame.index, "time": round(time.time(), 3),
            "age_s": round(time.monotonic() - frame.read_at, 4), "dropped": frame.dropped,
            "dropped_share": round(stream.dropped_share, 4), "reconnects": stream.reconnects,
            "status": state.status, "epoch": state.epoch, "restarted": state.restarted,
            "fused_focal_px": state.focal_px, "fused_roll_deg": state.roll_deg, "fused_tilt_deg": state.tilt_deg,
            "fused_pan_deg": state.pan_deg, "fused_sigma_roll_deg": sigma.get("roll_deg"),
            "fused_sigma_tilt_deg": sigma.get("tilt_deg"), "fused_sigma_focal_pct": sigma.get("focal_pct"),
            **{f"fused_horizon_{key}": horizon.get(key) for key in ("left_y", "right_y", "bound_pct", "unbounded")},
            "n_fused": state.n_fused, "disagreement": state.disagreement,
            **flat_record(result_record(result))}


def _csv_value(value: Any) -> Any:
    """A record's value in a CSV cell: empty for None / NaN, one line for text."""
    if value is None or (isinstance(value, float) and not math.isfinite(value)):
        return ""
    if isinstance(value, (np.floating, np.integer, np.bool_)):
        return _csv_value(value.item())
    if isinstance(value, str):
        return redact_text(" ".join(value.splitlines()))
    return value


def _now() -> str:
    return datetime.now(timezone.utc).isoformat(timespec="seconds")


@dataclass
class Totals:
    """Frames over every segment of an output folder (calibration.json's counters)."""

    processed: int = 0
    accepted: int = 0
    rejected: int = 0
    arrived: int = 0
    dropped: int = 0

    @classmethod
    def of(cls, summary: dict | None) -> Totals:
        summary = summary or {}
        return cls(*(int(summary.get(f"frames_{name}") or 0) for name in ("processed", "accepted", "rejected",
                                                                           "arrived", "dropped")))

    def json(self) -> dict[str, Any]:
        return {"frames_processed": self.processed, "frames_accepted": self.accepted,
                "frames_rejected": self.rejected, "frames_arrived": self.arrived, "frames_dropped": self.dropped,
                "dropped_share": round(self.dropped / self.arrived, 4) if self.arrived else 0.0}


class TrackOutput:
    """The output folder of one ``fr track`` run (module docstring): opens or resumes it, appends
    records, rewrites calibration.json, draws the figure.

    After opening: ``segment`` (this run's), ``start_frame`` (a file's first frame to process),
    ``checkpoint`` (the fusion to continue from, or None), ``resumed``.  ``settings`` (dict) and
    ``mode`` go into calibration.json as given.  ``json_target``: None, ``-`` (standard output) or
    a path for the JSON lines.  ``camera``: the camera's name in a fleet (:mod:`fr_torch.video.fleet`):
    every record then starts with a ``camera`` column (:data:`CAMERA_KEY`) and calibration.json
    names it; None (one source): the columns are :data:`RECORD_KEYS`.
    """

    def __init__(self, folder: Path, source: Source, settings: dict[str, Any], mode: str,
                 json_target: str | None = None, reliability_model: bool = True,
                 log: Callable[[str], None] = log_line, camera: str | None = None):
        self.folder = output_folder(Path(folder), "--out")
        self.source, self.settings, self.mode, self.log = source, settings, mode, log
        self.camera = camera
        self.keys = RECORD_KEYS if camera is None else (CAMERA_KEY,) + RECORD_KEYS
        self.reliability_model = reliability_model
        self.records_path = self.folder / RECORDS_FILE
        self.calibration_path = self.folder / CALIBRATION_FILE
        self.figure_path = self.folder / FIGURE_FILE
        previous = self._previous_summary()
        last = self._last_record()
        if previous is not None and previous.get("source") != str(source):
            raise FRInputError(f"--out {self.folder}: holds the records of {previous.get('source')!r}, not of "
                               f"{str(source)!r}; use another --out")
        self.resumed = previous is not None or last is not None
        self.segment = max(int(last["segment"]) if last else -1,
                           int(previous.get("segment", -1)) if previous else -1) + 1
        self.start_frame = int(last["frame"]) + 1 if last is not None and not source.live else 0
        self.checkpoint = previous.get("fusion") if previous else None
        self.totals = Totals.of(previous)
        self.segments = list((previous or {}).get("segments") or [])
        self.restarts = list((previous or {}).get("restarts_at_frames") or [])
        self.calibration: dict | None = (previous or {}).get("calibration")
        self.processed = 0  # this segment's records
        self.last_reliable = False  # whether the latest record's frame was reliable
        self.last_accepted_at: float | None = None  # Unix time of the latest accepted frame's record
        self.started = _now()
        self._records = self._open_records()
        self._json: TextIO | None = None
        if json_target == "-":
            self._json = sys.stdout
        elif json_target:
            try:
                self._json = open(json_target, "a", encoding="utf-8")
            except OSError as exc:
                raise FRInputError(f"--json {json_target}: cannot write ({exc.strerror or exc})") from None

    # ------------------------------------------------------------ reading what is there

    def _previous_summary(self) -> dict | None:
        if not self.calibration_path.exists():
            return None
        try:
            summary = json.loads(self.calibration_path.read_text())
        except (OSError, ValueError) as exc:
            raise FRInputError(f"{self.calibration_path}: cannot read ({exc}); use another --out") from None
        if not isinstance(summary, dict):
            raise FRInputError(f"{self.calibration_path}: not an fr track calibration; use another --out")
        return summary

    def _last_record(self) -> dict | None:
        """The last complete record of frames.csv (None without one), after removing a last line
        cut short and checking the columns."""
        path = self.records_path
        if not path.exists():
            return None
        size = path.stat().st_size
        with open(path, "rb+") as handle:
            tail_start = max(0, size - 65536)
            handle.seek(tail_start)
            tail = handle.read()
            if tail and not tail.endswith(b"\n"):
                cut = tail.rfind(b"\n")
                keep = tail_start + cut + 1 if cut >= 0 else 0
                handle.truncate(keep)
                self.log(f"fr track: {path}: removed a last record cut short ({size - keep} bytes)")
                tail = tail[:cut + 1] if cut >= 0 else b""
            handle.seek(0)
            header = handle.readline().decode("utf-8", "replace").rstrip("\r\n")
        if not header:
            return None
        if header.split(",") != list(self.keys):
            raise FRInputError(f"{path}: its columns are not those of this fr track ({header[:60]}...); use "
                               "another --out")
        lines = tail.splitlines()
        if len(lines) < 2 and tail_start == 0:
            return None
        row = next(csv.DictReader(io.StringIO(header + "\n" + lines[-1].decode("utf-8", "replace"))))
        try:
            return {"segment": int(row["segment"]), "frame": int(row["frame"])}
        except (TypeError, ValueError):
            raise FRInputError(f"{path}: its last record is not readable; use another --out") from None

    def _open_records(self):
        new = not self.records_path.exists() or self.records_path.stat().st_size == 0
        try:
            handle = open(self.records_path, "a", newline="", encoding="utf-8")
        except OSError as exc:
            raise FRInputError(f"cannot write {self.records_path}: {exc.strerror or exc}") from None
        writer = csv.writer(handle, lineterminator="\n")
        if new:
            writer.writerow(self.keys)
            handle.flush()
        return handle, writer

    # ------------------------------------------------------------ writing

    def append(self, record: dict[str, Any]) -> None:
        """Append one record to frames.csv (and the JSON lines), each flushed at once."""
        if self.camera is not None:
            record = {CAMERA_KEY: self.camera, **record}
        handle, writer = self._records
        writer.writerow([_csv_value(record[key]) for key in self.keys])
        handle.flush()
        if self._json is not None:
            self._json.write(dumps(record) + "\n")
            self._json.flush()
        self.processed += 1
        self.totals.processed += 1
        self.totals.accepted += record["status"] in ACCEPTED
        self.last_reliable = bool(record["reliable"])
        if record["status"] in ACCEPTED:
            self.last_accepted_at = record["time"]
        self.totals.rejected += record["status"] == "rejected"
        if record["restarted"]:
            self.restarts = (self.restarts + [record["frame"]])[-KEPT_ENTRIES:]

    def write_calibration(self, state: FusedState | None, checkpoint: dict[str, Any], stream: FrameStream,
                          run: str = "running") -> None:
        """Rewrite calibration.json atomically: ``state`` the fused state (None: keep the last
        one written), ``checkpoint`` the fusion's, ``stream`` this segment's counters, ``run``
        ``running`` or how the run ended."""
        if state is not None and state.valid:
            self.calibration = fused_calibration(state)
        segment = {"segment": self.segment, "started": self.started, "first_frame": self.start_frame,
                   "frames_processed": self.processed, "frames_arrived": stream.arrived,
                   "frames_dropped": stream.dropped, "frames_skipped": stream.skipped,
                   "dropped_share": round(stream.dropped_share, 4), "reconnects": stream.reconnects, "run": run}
        totals = Totals(self.totals.processed, self.totals.accepted, self.totals.rejected,
                        self.totals.arrived + stream.arrived, self.totals.dropped + stream.dropped)
        camera = {} if self.camera is None else {CAMERA_KEY: self.camera}
        summary = {**camera, "source": str(self.source), "live": self.source.live, "mode": self.mode,
                   "reliability_model": self.reliability_model, "settings": self.settings,
                   "run": run, "updated": _now(), "segment": self.segment,
                   **totals.json(), "restarts_at_frames": self.restarts,
                   "segments": (self.segments + [segment])[-KEPT_ENTRIES:],
                   "calibration": self.calibration, "fusion": checkpoint}
        write_text_atomic(self.calibration_path, dumps(summary, indent=1) + "\n")

    def close(self) -> None:
        handle, _ = self._records
        handle.close()
        if self._json is not None and self._json is not sys.stdout:
            self._json.close()

    def plot(self, title: str = "") -> Path | None:
        """Draw track.png from the latest records (None when there are none)."""
        return plot_records(self.records_path, self.figure_path, title, live=self.source.live)


# ---------------------------------------------------------------------------------- reading back

def read_records(path: Path, last: int | None = PLOT_RECORDS) -> pd.DataFrame:
    """The latest ``last`` records of a frames.csv (all with None), read in chunks so that memory
    stays bounded by ``last`` however long the file."""
    tail: deque = deque()
    kept = 0
    for chunk in pd.read_csv(path, chunksize=10_000):
        tail.append(chunk)
        kept += len(chunk)
        while last is not None and tail and kept - len(tail[0]) >= last:
            kept -= len(tail.popleft())
    if not tail:
        return pd.DataFrame(columns=list(RECORD_KEYS))
    table = pd.concat(list(tail), ignore_index=True)
    return table if last is None else table.iloc[-last:].reset_index(drop=True)


def plot_records(records_path: Path, figure_path: Path, title: str = "", live: bool = False,
                 last: int = PLOT_RECORDS) -> Path | None:
    """Draw :func:`plot_track` of the latest ``last`` records of ``records_path`` into
    ``figure_path`` (written atomically); None when there is no record."""
    if not records_path.exists():
        return None
    table = read_records(records_path, last)
    if table.empty:
        return None
    buffer = io.BytesIO()
    plot_track(table, buffer, title, live=live)
    write_bytes_atomic(figure_path, buffer.getvalue())
    return figure_path


def plot_track(records: pd.DataFrame, target, title: str = "", live: bool = False) -> None:
    """Per-frame estimates with predicted error bars (up to :data:`ERROR_BAR_RECORDS` records;
    dots beyond), held and rejected frames, the fused track and its restarts (dashed), against the
    frame index, or for a live source (``live``) against the time since the first record (s), with
    the start of each segment (dotted).  ``records``: rows of :data:`RECORD_KEYS`; ``target``: a
    path or a binary file (PNG)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(4, 1, figsize=(9, 9), sharex=True)
    panels = [("roll_deg", "predicted_error_roll_deg", "fused_roll_deg", "roll (deg)"),
              ("tilt_deg", "predicted_error_tilt_deg", "fused_tilt_deg", "tilt (deg)"),
              ("focal_px", "predicted_error_focal_pct", "fused_focal_px", "focal (px)"),
              ("pan_deg", None, "fused_pan_deg", "pan (deg, folded)")]

    def column(key) -> np.ndarray:
        return pd.to_numeric(records[key], errors="coerce").to_numpy(float)

    times = column("time")
    x = times - times[0] if live else column("frame")
    status = records["status"].astype(str).to_numpy()
    good, held = np.isin(status, ACCEPTED), status == "held"
    rejected = ~good & ~held
    restarts = x[records["restarted"].astype(str).str.lower().eq("true").to_numpy()]
    segment = column("segment")
    segment_starts = x[1:][np.diff(segment) != 0]
    bars = len(records) <= ERROR_BAR_RECORDS
    for ax, (estimate, error, fused, label) in zip(axes, panels):
        y = column(estimate)
        if error is not None and bars:
            e = np.nan_to_num(column(error) / 100.0 * y if estimate == "focal_px" else column(error), nan=0.0)
            ax.errorbar(x[good], y[good], yerr=e[good], fmt="o", ms=3, color="tab:blue", alpha=0.8,
                        elinewidth=0.8, label="accepted (predicted error)")
            ax.errorbar(x[held], y[held], yerr=e[held], fmt="s", ms=3, color="tab:orange", alpha=0.8,
                        elinewidth=0.8, label="held (disagrees)")
        else:
            size = 3 if bars else 1.5
            ax.plot(x[good], y[good], "o", ms=size, color="tab:blue", label="accepted")
            ax.plot(x[held], y[held], "s", ms=size, color="tab:orange", label="held (disagrees)")
        ax.plot(x[rejected], y[rejected], "x", ms=4, color="grey", label="rejected (unreliable)")
        ax.plot(x, column(fused), "-", color="tab:red", lw=1.5, label="fused", zorder=3)
        for at in restarts:
            ax.axvline(at, color="k", ls="--", lw=0.8)
        for at in segment_starts:
            ax.axvline(at, color="tab:green", ls=":", lw=1.0)
        ax.set_ylabel(label)
        ax.grid(alpha=0.3)
    axes[0].legend(fontsize=7, ncol=4, loc="best")
    axes[-1].set_xlabel(("seconds since the first record" if live else "frame")
                        + " (dashed: camera moved, fusion restarted; dotted: a new run)")
    if title:
        fig.suptitle(title)
    fig.tight_layout()
    fig.savefig(target, dpi=100, format="png")
    plt.close(fig)
