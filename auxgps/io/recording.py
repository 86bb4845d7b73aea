"""Recordings of what the estimator saw in a flight, and reading them back.

A recording is a folder:

- ``flight.tlog``: every MAVLink message from the autopilot as it arrived, in the standard tlog framing (a
  big-endian 64-bit microsecond UTC stamp before each message), which pymavlink's tools (``mavlogdump.py``,
  MAVExplorer) read. The stamp is the arrival on the companion's monotonic clock plus a fixed offset
  (``clock_offset_us`` in ``recording.json``), so that the monotonic arrival is recovered to the microsecond;
- ``frames/NNNNNN.png`` and ``frames.csv`` (index, capture time on the same monotonic clock, file): every frame
  the estimator began, lossless, so that a replay detects the same features;
- ``journal.csv``: the order of the estimator's calls that are not messages (a frame begun, a frame finished,
  GPS_INPUT asked for), each after the count of messages fed before it: with the tlog it fixes the order of
  every call the companion's threads made under their lock, so that a replay makes the same calls in the same
  order and gets the same results;
- ``recording.json``: the format, the clock offset, the companion's options and the pipeline configuration it
  started with, and ``start_map.npz``, the map it started with (when it had one).

Recording costs the frame thread a row in two CSV files and a queue put; the PNGs are written by a thread of
their own. Frames the writer cannot keep up with (a queue of ``max_queue`` frames) are not recorded, counted and
logged, never waited for: recording must not slow the flight.
"""

from __future__ import annotations

import csv
import itertools
import json
import logging
import queue
import shutil
import struct
import threading
import time
from collections import deque
from collections.abc import Iterable, Iterator
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field
from pathlib import Path

import cv2
import numpy as np

from auxgps.core.events import Frame
from auxgps.errors import RecordingError

log = logging.getLogger(__name__)

FORMAT = "auxgps-recording"
VERSION = 1
#: Frames are written losslessly, zlib level 1, each row filtered by its left neighbour ("sub") rather than by the
#: best of five filters tried per row: a 1280 x 720 simulated frame encodes in 7.5 ms instead of 28 ms, to the same
#: size, and a real one (a Brighton photo at that size) in 87 ms instead of 96 ms, 7 % larger.
PNG_PARAMS = [cv2.IMWRITE_PNG_COMPRESSION, 1, cv2.IMWRITE_PNG_FILTER, cv2.IMWRITE_PNG_FILTER_SUB]


class Recorder:
    """Writes a recording while the companion flies. Every method but :meth:`close` is called with the
    companion's estimator lock held, in the order of the calls it records."""

    def __init__(self, folder: str | Path, *, options: dict, pipeline: dict, start_map: str | None, max_queue: int = 64) -> None:
        self.folder = Path(folder)
        (self.folder / "frames").mkdir(parents=True, exist_ok=True)
        self.clock_offset_us = int(round((time.time() - time.monotonic()) * 1e6))
        meta = {"format": FORMAT, "version": VERSION, "clock_offset_us": self.clock_offset_us, "options": options,
                "pipeline": pipeline, "start_map": "start_map.npz" if start_map else None}
        if start_map and Path(start_map).resolve() != (self.folder / "start_map.npz").resolve():
            shutil.copyfile(start_map, self.folder / "start_map.npz")
        (self.folder / "recording.json").write_text(json.dumps(meta, indent=2))
        self._tlog = open(self.folder / "flight.tlog", "wb")
        self._journal_file = open(self.folder / "journal.csv", "w", newline="")
        self._journal = csv.writer(self._journal_file)
        self._journal.writerow(["n_messages", "call", "a", "b"])
        self._frames_file = open(self.folder / "frames.csv", "w", newline="")
        self._frames = csv.writer(self._frames_file)
        self._frames.writerow(["index", "t_s", "file"])
        self.n_messages = 0
        self.n_frames = 0
        self.n_dropped = 0
        self.write_ms: list[float] = []
        self.enqueue_ms: list[float] = []
        self._queue: queue.Queue = queue.Queue(maxsize=max_queue)
        self._writer = threading.Thread(target=self._write_frames, daemon=True, name="recorder")
        self._writer.start()

    def message(self, msg, arrival_s: float) -> None:
        """A message as it arrived (``arrival_s`` on the monotonic clock, whole microseconds)."""
        stamp_us = int(round(arrival_s * 1e6)) + self.clock_offset_us
        self._tlog.write(struct.pack(">Q", stamp_us) + bytes(msg.get_msgbuf()))
        self.n_messages += 1

    def begin(self, frame: Frame) -> int:
        """A frame the estimator is about to begin; returns its index."""
        t0 = time.perf_counter()
        k = self.n_frames
        self.n_frames += 1
        name = f"frames/{k:06d}.png"
        self._frames.writerow([k, repr(float(frame.t_s)), name])
        self._journal.writerow([self.n_messages, "begin", k, ""])
        try:
            self._queue.put_nowait((name, frame.image_bgr))
        except queue.Full:
            self.n_dropped += 1
            log.warning("recording: frame %d not written (the writer is %d frames behind)", k, self._queue.maxsize)
        self.enqueue_ms.append((time.perf_counter() - t0) * 1e3)
        return k

    def finish(self, k: int) -> None:
        self._journal.writerow([self.n_messages, "finish", k, ""])

    def output(self, t_s: float, t_unix_s: float) -> None:
        """GPS_INPUT asked for at ``t_s`` (monotonic) and ``t_unix_s`` (UTC). Flushes the logs: at most a tenth
        of a second is lost in a crash."""
        self._journal.writerow([self.n_messages, "output", repr(float(t_s)), repr(float(t_unix_s))])
        self._tlog.flush()
        self._journal_file.flush()
        self._frames_file.flush()

    def _write_frames(self) -> None:
        while True:
            item = self._queue.get()
            if item is None:
                return
            name, image = item
            t0 = time.perf_counter()
            ok = cv2.imwrite(str(self.folder / name), image, PNG_PARAMS)
            self.write_ms.append((time.perf_counter() - t0) * 1e3)
            if not ok:
                log.warning("recording: could not write %s", name)

    def close(self) -> dict:
        """Finish writing; return and store what recording cost (``recording_stats.json``)."""
        self._queue.put(None)
        self._writer.join(timeout=30)
        for f in (self._tlog, self._journal_file, self._frames_file):
            f.close()
        stats = {
            "messages": self.n_messages,
            "frames": self.n_frames,
            "frames_not_written": self.n_dropped,
            "frame_thread_ms_per_frame": _median(self.enqueue_ms),
            "png_write_ms_per_frame": _median(self.write_ms),
        }
        (self.folder / "recording_stats.json").write_text(json.dumps(stats, indent=2))
        return stats


def _median(x: list[float]) -> float | None:
    return float(np.median(x)) if x else None


# -- reading ------------------------------------------------------------------------------------------------


@dataclass
class JournalEntry:
    n_messages: int
    call: str  # "begin", "finish" or "output"
    frame: int | None = None
    t_s: float | None = None
    t_unix_s: float | None = None


@dataclass
class Recording:
    """A recording opened for replay. ``problems`` gathers one line per thing found wrong while reading."""

    folder: Path
    meta: dict
    journal: list[JournalEntry]
    frames: dict[int, tuple[float, Path]]  # index -> (capture time s, file)
    problems: list[str] = field(default_factory=list)

    @property
    def clock_offset_us(self) -> int:
        return int(self.meta["clock_offset_us"])

    def messages(self):
        """(message, arrival on the monotonic clock, s) for each message of the tlog, in order, as far as it can be
        read; a cut or corrupt tlog ends the messages with a line in ``problems``."""
        import os

        os.environ.setdefault("MAVLINK20", "1")
        from pymavlink import mavutil

        path = self.folder / "flight.tlog"
        try:
            mlog = mavutil.mavlink_connection(str(path), robust_parsing=True)
        except OSError as err:
            self.problems.append(f"{path}: cannot be read ({err}); no messages")
            return
        n_bad = 0
        last_us = None
        try:
            while True:
                try:
                    msg = mlog.recv_msg()
                except Exception as err:  # noqa: BLE001 - pymavlink raises several kinds on a damaged file
                    self.problems.append(f"{path}: unreadable from byte {mlog.f.tell()} ({type(err).__name__}: {err}); replayed as far as it goes")
                    return
                if msg is None:
                    break
                if msg.get_type() == "BAD_DATA":
                    n_bad += 1
                    continue
                stamp_us = int(round(msg._timestamp * 1e6))
                if last_us is not None and stamp_us < last_us:
                    self.problems.append(f"{path}: a message stamped {(last_us - stamp_us) / 1e6:.3f} s before the one before it")
                last_us = stamp_us
                yield msg, (stamp_us - self.clock_offset_us) / 1e6
        finally:
            if n_bad:
                self.problems.append(f"{path}: {n_bad} stretches of bytes that are not MAVLink skipped")
            mlog.close()

    def image(self, k: int) -> np.ndarray | None:
        """Frame ``k``'s image, or None (with a line in ``problems``) when it is missing or unreadable."""
        if k not in self.frames:
            self.problems.append(f"frame {k}: not in frames.csv; skipped")
            return None
        path = self.frames[k][1]
        image = cv2.imread(str(path), cv2.IMREAD_COLOR) if path.exists() else None
        if image is None:
            self.problems.append(f"frame {k}: {path.name} missing or unreadable; skipped")
        return image

    def images(self, ks: Iterable[int], ahead: int = 8) -> Iterator[np.ndarray | None]:
        """:meth:`image` of each of ``ks`` in turn, read by a thread up to ``ahead`` frames before it is asked for:
        decoding a PNG frame takes about half as long as locating the vehicle in it, and OpenCV lets go of the
        interpreter while it decodes, so a replay on two cores need not wait for its frames."""
        ks = iter(ks)
        with ThreadPoolExecutor(max_workers=1, thread_name_prefix="replay-frames") as pool:
            pending = deque(pool.submit(self.image, k) for k in itertools.islice(ks, ahead))
            while pending:
                image = pending.popleft().result()
                pending.extend(pool.submit(self.image, k) for k in itertools.islice(ks, 1))
                yield image


def open_recording(folder: str | Path) -> Recording:
    """Open a recording; a folder that is not one is a :class:`RecordingError`, damage inside it is a problem line."""
    folder = Path(folder)
    meta_path = folder / "recording.json"
    try:
        meta = json.loads(meta_path.read_text())
    except FileNotFoundError:
        raise RecordingError(f"{folder}: not a recording (no recording.json)") from None
    except (OSError, ValueError) as err:
        raise RecordingError(f"{meta_path}: unreadable ({err})") from None
    if not isinstance(meta, dict) or meta.get("format") != FORMAT:
        raise RecordingError(f"{meta_path}: not an auxgps recording")
    if meta.get("version") != VERSION:
        raise RecordingError(f"{meta_path}: recording version {meta.get('version')} (this auxgps reads {VERSION})")
    if not (folder / "flight.tlog").exists():
        raise RecordingError(f"{folder}: no flight.tlog")
    problems: list[str] = []
    frames: dict[int, tuple[float, Path]] = {}
    last_t = -np.inf
    for line, row in _csv_rows(folder / "frames.csv", problems):
        try:
            k, t = int(row["index"]), float(row["t_s"])
        except (KeyError, TypeError, ValueError):
            problems.append(f"frames.csv line {line}: unreadable; skipped")
            continue
        if not np.isfinite(t) or t < last_t:
            problems.append(f"frames.csv line {line}: frame {k} at {t} s is out of time order; skipped")
            continue
        last_t = t
        frames[k] = (t, folder / row.get("file", f"frames/{k:06d}.png"))
    journal: list[JournalEntry] = []
    for line, row in _csv_rows(folder / "journal.csv", problems):
        try:
            n, call = int(row["n_messages"]), row["call"]
            if call in ("begin", "finish"):
                journal.append(JournalEntry(n, call, frame=int(row["a"])))
            elif call == "output":
                journal.append(JournalEntry(n, call, t_s=float(row["a"]), t_unix_s=float(row["b"])))
            else:
                raise ValueError(call)
        except (KeyError, TypeError, ValueError):
            problems.append(f"journal.csv line {line}: unreadable; skipped")
    return Recording(folder, meta, journal, frames, problems)


def _csv_rows(path: Path, problems: list[str]):
    """(line number, row) of a CSV file; a missing file or a cut last line is a problem line."""
    try:
        text = path.read_text()
    except OSError as err:
        problems.append(f"{path.name}: cannot be read ({err.strerror or err})")
        return
    lines = text.splitlines()
    if text and not text.endswith("\n"):
        problems.append(f"{path.name}: its last line is cut; skipped")
        lines = lines[:-1]
    for k, row in enumerate(csv.DictReader(lines), start=2):
        yield k, row
