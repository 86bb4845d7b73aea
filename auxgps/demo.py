"""The closed-loop demo: the vehicle emulator and `auxgps run` as separate processes on loopback.

The emulator flies the survey on GPS1; GPS1 is disabled part-way; the rest of the survey and the return home
are flown on auxgps's GPS2. A control run without auxgps shows what happens otherwise. The report is a PNG and a
JSON of the figures. The emulator (:mod:`auxgps.sim.emulator`) is a stand-in for the autopilot, started as a
process of its own, never imported here.
"""

from __future__ import annotations

import json
import queue
import socket
import subprocess
import sys
import threading
import time
from pathlib import Path

import numpy as np
from tqdm import tqdm


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def _emulator(world: str, port: int, log: Path, flight: list[str], gps2_type: int, max_s: float) -> subprocess.Popen:
    cmd = [sys.executable, "-m", "auxgps.sim.emulator", "--world", world, "--port", str(port), *flight,
           "--gps2-type", str(gps2_type), "--log", str(log), "--max-seconds", str(max_s)]
    return subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)


def run_demo(world: str, out_dir: str = "out/demo", fail_at_s: float = 60.0, max_s: float = 480.0,
             mission: tuple[str, ...] = (), sim_camera_fps: float | None = None) -> dict:
    """Fly the closed loop and the control run at once; return the figures (also written as JSON and PNG).
    ``mission``: the emulator's options that fly a mission instead of the survey (``--mission``, ``--speed-m-s``,
    ``--gps-lost-at-waypoint``); GPS1 then fails where they say instead of ``fail_at_s`` after take-off.
    ``sim_camera_fps``: the simulated camera delivers that many frames a second (`auxgps run --sim-camera-fps`)
    instead of one per frame loop."""
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    port, port_ctl = _free_port(), _free_port()
    flight = list(mission) if mission else ["--fail-gps1-at", str(fail_at_s)]
    emu = _emulator(world, port, out / "emulator.json", flight, 14, max_s)
    ctl = _emulator(world, port_ctl, out / "control.json", flight, 0, max_s)
    time.sleep(1.0)
    run = subprocess.Popen(
        [sys.executable, "-m", "auxgps.cli", "run", "--connect", f"tcp:127.0.0.1:{port}", "--camera", f"sim:{world}",
         "--log-dir", str(out / "run"), "--duration", str(max_s),
         *(["--sim-camera-fps", str(sim_camera_fps)] if sim_camera_fps else [])],
        stdout=open(out / "run.log", "w"), stderr=subprocess.STDOUT,
    )
    events: queue.Queue[str] = queue.Queue()

    def pump() -> None:  # the emulator's lines, read off the main loop so that the progress bar keeps moving
        for line in emu.stdout:
            if ("EMU:" in line or "Failsafe" in line or "GPS" in line) and "PreArm" not in line:
                events.put(line.strip().split(" INFO ")[-1])

    threading.Thread(target=pump, daemon=True).start()
    try:
        with tqdm(total=int(max_s), desc="closed-loop flight", unit="s") as bar:
            t0 = time.monotonic()
            while emu.poll() is None and time.monotonic() - t0 < max_s + 30:
                time.sleep(0.5)
                while not events.empty():
                    bar.write("  " + events.get())
                bar.n = min(int(time.monotonic() - t0), int(max_s))
                bar.refresh()
    finally:
        for p in (run, emu):
            if p.poll() is None:
                p.terminate()
        run.wait(timeout=10)
        ctl.wait(timeout=max_s + 60)
    return report(out)


def report(out: Path) -> dict:
    """Figures and a PNG from the emulator's logs of the auxgps run and of the control run."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    log = json.loads((out / "emulator.json").read_text())
    ctl = json.loads((out / "control.json").read_text())
    s = log["samples"]
    t = np.array([x["t_s"] for x in s])
    truth = np.array([x["truth_ned_m"] for x in s])
    est = np.array([x["estimate_ned_m"] for x in s])
    fail = log.get("failure_t_s")
    err = np.linalg.norm(truth[:, :2] - est[:, :2], axis=1)
    denied = t >= fail if fail is not None else np.zeros(len(t), bool)
    arrivals = np.array(log.get("gps_input_arrivals_t_s", []))
    # The descent to the landing: how far GPS2 (what auxgps last said) was from the truth, against its accuracy
    down = [x for x in s if x.get("phase") == "descend" and x.get("gps2_ned_m") is not None and x.get("gps2_fix") == 3]
    gps2_err = np.array([np.hypot(*np.subtract(x["gps2_ned_m"][:2], x["truth_ned_m"][:2])) for x in down])
    gps2_acc = np.array([x["gps2_h_acc_m"] for x in down])
    figures = {
        "landing_error_m": log.get("landing_error_m"),
        "gps2_switch_s": (log["switch_to_gps2_t_s"] - fail) if fail is not None and log.get("switch_to_gps2_t_s") else None,
        "gps_input": log.get("gps_input"),
        "denied_s": float(t[denied][-1] - fail) if denied.any() else 0.0,
        "horizontal_error_m": {"rms": float(np.sqrt(np.mean(err[denied] ** 2))) if denied.any() else None,
                               "max": float(err[denied].max()) if denied.any() else None},
        "descent": {"gps2_3d_samples": len(down),
                    "gps2_error_max_m": float(gps2_err.max()) if len(down) else None,
                    "gps2_within_3_reported": float(np.mean(gps2_err <= 3.0 * gps2_acc)) if len(down) else None},
        "exit": log.get("exit_reason"),
        "frames": json.loads((out / "run" / "frames.json").read_text()) if (out / "run" / "frames.json").exists() else None,
        "control": {"landing_error_m": ctl.get("landing_error_m"), "exit": ctl.get("exit_reason"),
                    "failsafe": any(e.get("event") == "failsafe" for e in ctl.get("events", []))},
    }
    fig, ax = plt.subplots(1, 3, figsize=(16, 5))
    ax[0].plot(truth[:, 1], truth[:, 0], label="true path")
    ax[0].plot(est[:, 1], est[:, 0], label="autopilot's estimate", alpha=0.7)
    if fail is not None:
        k = int(np.searchsorted(t, fail))
        ax[0].plot(truth[k, 1], truth[k, 0], "rx", ms=12, label="GPS1 fails")
    c = ctl["samples"]
    ax[0].plot([x["truth_ned_m"][1] for x in c], [x["truth_ned_m"][0] for x in c], ":", label="control run (no auxgps)")
    ax[0].plot(0, 0, "k^", label="home")
    ax[0].set(xlabel="east (m)", ylabel="north (m)", title="flight", aspect="equal")
    ax[0].legend(fontsize=8)
    ax[1].plot(t, err)
    if fail is not None:
        ax[1].axvline(fail, color="r", ls="--", label="GPS1 fails")
    ax[1].set(xlabel="time (s)", ylabel="m", title="autopilot's horizontal error")
    ax[1].legend()
    if len(arrivals) > 1:
        ax[2].plot(arrivals[1:], np.diff(arrivals) * 1000.0, ".", ms=2)
        ax[2].axhline(215, color="r", ls="--", label="ArduPilot's mean limit 215 ms")
        ax[2].axhline(245, color="m", ls=":", label="gap limit 245 ms")
    ax[2].set(xlabel="time (s)", ylabel="ms", title="interval between GPS_INPUT messages")
    ax[2].legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(out / "report.png", dpi=90)
    (out / "report.json").write_text(json.dumps(figures, indent=2))
    return figures
