"""Memory of a process that records, at the daemon's rates, over minutes: the Recorder as it is against its
earlier configuration (an .rrd footer, the SDK's default batching) and against a footer with the new batching,
all run side by side for the same time.

Each configuration runs in its own process and logs what the daemon logs, paced by the wall clock (the SDK's
batcher flushes on wall time, so only real pacing gives the daemon's chunk counts): telemetry 50 Hz (three
scalars per chamber), volumes 10 Hz (gland target, estimate, true; three chambers), link 2 Hz, a 1,000-vertex
mesh 1 Hz, an event every 10 s. RSS is sampled every 30 s; the table shows it and the growth rate over the
second half (after the SDK's start-up allocations).

    .venv/bin/python bench/recording_memory.py [--minutes 6] [--out out/recording_memory]
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

CONFIGURATIONS = {
    "now": {},
    "footer, 0.5 s batching": {"WRITE_FOOTER": True},
    "before (footer, default batching)": {"WRITE_FOOTER": True, "FLUSH_TICK_S": None},
}
NAMES = ["base", "left lobe", "right lobe"]
SAMPLE_S = 30.0


def rss_mb() -> float:
    with open("/proc/self/status") as status:
        for line in status:
            if line.startswith("VmRSS:"):
                return int(line.split()[1]) / 1024
    raise RuntimeError("no VmRSS in /proc/self/status")


def sphere_mesh(radius_mm: float = 20.0, rings: int = 22, segments: int = 46) -> tuple[np.ndarray, np.ndarray]:
    """About 1,000 vertices, like the daemon's outer surface (the triangles need not be a closed surface here)."""
    polar, azimuth = np.meshgrid(np.linspace(0.05, np.pi - 0.05, rings), np.linspace(0, 2 * np.pi, segments,
                                                                                       endpoint=False), indexing="ij")
    points = radius_mm * np.stack([np.sin(polar) * np.cos(azimuth), np.sin(polar) * np.sin(azimuth), np.cos(polar)],
                                  axis=-1).reshape(-1, 3)
    index = np.arange(rings * segments).reshape(rings, segments)
    right = np.roll(index, -1, axis=1)
    quads = np.stack([index[:-1], index[1:], right[1:], right[:-1]], axis=-1).reshape(-1, 4)
    return points, np.vstack([quads[:, [0, 1, 2]], quads[:, [0, 2, 3]]])


def child(configuration: str, minutes: float, path: Path) -> None:
    """Record for ``minutes`` at the daemon's rates; print one JSON line per RSS sample."""
    from phantom.host import recording

    for name, value in CONFIGURATIONS[configuration].items():
        setattr(recording, name, value)
    rng = np.random.default_rng(0)
    rest, triangles = sphere_mesh()
    recorder = recording.Recorder(NAMES, save_path=path)
    recorder.open()
    recorder.log_rest_surface(rest, triangles)
    period_s, frame = 0.02, 0
    started = time.monotonic()
    next_sample_s = 0.0
    while (time_s := frame * period_s) <= minutes * 60:
        recorder.set_scene_time(time_s - 5.0 if time_s >= 5.0 else None)
        recorder.log_telemetry(time_s, rng.random(3), rng.random(3), rng.random(3))
        if frame % 5 == 0:
            recorder.log_volumes(time_s, 30.0, 30 + rng.random(), 2 + rng.random(3), true_ml=31 + rng.random())
        if frame % 25 == 0:
            recorder.log_link(time_s, 3 + rng.random(), 0, 0, 0)
        if frame % 50 == 0:
            recorder.log_mesh(time_s, rest * (1 + 0.05 * rng.random()), triangles)
        if frame % 500 == 0:
            recorder.log_event(time_s, f"event at {time_s:.0f} s")
        if time_s >= next_sample_s:
            print(json.dumps({"time_s": time_s, "rss_mb": rss_mb()}), flush=True)
            next_sample_s += SAMPLE_S
        frame += 1
        time.sleep(max(0.0, started + frame * period_s - time.monotonic()))
    recorder.close()
    print(json.dumps({"time_s": minutes * 60, "rss_mb": rss_mb(), "closed": True}), flush=True)


def growth_mb_per_min(samples: list[dict]) -> float:
    """Least-squares slope of RSS over the second half of the run (MB per minute)."""
    times = np.array([s["time_s"] for s in samples if not s.get("closed")])
    rss = np.array([s["rss_mb"] for s in samples if not s.get("closed")])
    half = times >= times[-1] / 2
    return float(np.polyfit(times[half] / 60, rss[half], 1)[0])


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--minutes", type=float, default=6.0, help="recording time of each configuration")
    parser.add_argument("--out", default="out/recording_memory", help="folder for the recordings and the plot")
    parser.add_argument("--child", help=argparse.SUPPRESS)
    args = parser.parse_args()
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    if args.child:
        child(args.child, args.minutes, out / f"{list(CONFIGURATIONS).index(args.child)}.rrd")
        return
    processes = {name: subprocess.Popen([sys.executable, __file__, "--child", name, "--minutes", str(args.minutes),
                                         "--out", str(out)], stdout=subprocess.PIPE, stderr=subprocess.DEVNULL,
                                        text=True)
                 for name in CONFIGURATIONS}
    samples = {name: [json.loads(line) for line in process.stdout] for name, process in processes.items()}
    for process in processes.values():
        process.wait()
    names = list(CONFIGURATIONS)
    print(f"RSS (MB) while recording at the daemon's rates, {args.minutes:g} min, the configurations side by side\n")
    print("| time min | " + " | ".join(names) + " |")
    print("|---|" + "---|" * len(names))
    for row in zip(*(samples[name] for name in names), strict=False):
        label = "after close" if row[0].get("closed") else f"{row[0]['time_s'] / 60:.1f}"
        print(f"| {label} | " + " | ".join(f"{sample['rss_mb']:.1f}" for sample in row) + " |")
    rates = {name: growth_mb_per_min(samples[name]) for name in names}
    sizes = {name: (out / f"{index}.rrd").stat().st_size / 1e6 for index, name in enumerate(names)}
    print("| growth, second half (MB/min) | " + " | ".join(f"{rates[name]:+.2f}" for name in names) + " |")
    print("| file size (MB) | " + " | ".join(f"{sizes[name]:.1f}" for name in names) + " |")
    try:
        import matplotlib

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt
    except ImportError:
        return
    figure, axis = plt.subplots(figsize=(7, 4))
    for name in names:
        live = [s for s in samples[name] if not s.get("closed")]
        axis.plot([s["time_s"] / 60 for s in live], [s["rss_mb"] for s in live], "o-", label=name)
    axis.set_xlabel("recording time (min)")
    axis.set_ylabel("RSS (MB)")
    axis.set_title("Memory while recording at the daemon's rates")
    axis.legend()
    axis.grid(alpha=0.3)
    figure.tight_layout()
    figure.savefig(out / "rss.png", dpi=100)
    print(f"\nplot: {out / 'rss.png'}")


if __name__ == "__main__":
    main()
