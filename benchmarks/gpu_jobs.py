"""A workflow run's GPU jobs: how busy each GPU was, the wall time against the jobs' sum, and what the same jobs
would have taken in another order.

    python benchmarks/gpu_jobs.py JOBS.md [MORE.md ...] [--smi smi.csv] [--gpus 4] [--plot gpu_jobs.png]

JOBS.md: job tables of benchmarks/job_timeline.py (a killed run's and its rerun's together: a failed job's seconds
count as spent). smi.csv: `nvidia-smi --query-gpu=timestamp,index,utilization.gpu,memory.used --format=csv -l 2`
during the run (benchmarks/gpu_runs/run23/slots.sh writes both).

The order table replays the run's completed jobs with their measured seconds on --gpus devices (list scheduling: a
free device takes the first ready GPU job in the order's rule ranking, CPU jobs start when ready), the
dependencies read from the rules and wildcards of the tables workflow (capture, preprocess, fit, render, evaluate,
tables). "downstream first" is what Snakemake's greedy scheduler picks among equal priorities (its reward is the
job's input bytes, larger for a render or an evaluate than for a fit); "fits first" is what a higher `priority:`
of fit_avatar makes it pick. One GPU: the same replay on one device.
"""
from __future__ import annotations

import argparse
import csv
import datetime
import re
from pathlib import Path

ORDERS = {  # rule ranks: lower starts first among ready GPU jobs
    "downstream first": {"evaluate": 0, "render_split": 1, "fit_avatar": 2},
    "fits first": {"fit_avatar": 0, "render_split": 1, "evaluate": 2},
}
TABLE_DAY = {"year": 2000, "month": 1, "day": 1}  # job tables give clock times of one run: every time on one day


def on_table_day(clock: str) -> datetime.datetime:
    return datetime.datetime.combine(datetime.date(**TABLE_DAY), datetime.time.fromisoformat(clock))


def read_jobs(paths: list[Path]) -> list[dict]:
    """Rows of job_timeline tables: {rule, wildcards (a dict), start, end (datetime), seconds, status, device}. A job
    killed in one run and done in the next keeps both rows."""
    jobs = []
    for path in paths:
        for line in path.read_text().splitlines():
            cells = [cell.strip() for cell in line.strip().strip("|").split("|")]
            if len(cells) != 9 or not cells[0].isdigit():
                continue
            _, rule, wildcards, start, end, seconds, status, _, device = cells
            jobs.append({"rule": rule, "wildcards": dict(re.findall(r"(\w+)=([^,]+)", wildcards)),
                         "start": on_table_day(start), "end": on_table_day(end) if end else None,
                         "seconds": float(seconds) if seconds else 0.0, "status": status,
                         "device": None if device == "-" else device})
    if not jobs:
        raise SystemExit(f"gpu_jobs: no job rows in {', '.join(map(str, paths))} (expected job_timeline.py tables)")
    return jobs


def depends_on(job: dict, other: dict) -> bool:
    """Whether `job` needs `other`'s output in the tables workflow."""
    need = {"preprocess_capture": ("generate_capture",), "fit_avatar": ("preprocess_capture",),
            "render_split": ("fit_avatar",), "evaluate": ("render_split",),
            "make_table": ("evaluate",), "make_tables": ("evaluate",), "all_tables": ("make_table", "make_tables")}
    if other["rule"] not in need.get(job["rule"], ()):
        return False
    shared = set(job["wildcards"]) & set(other["wildcards"])
    return all(job["wildcards"][key] == other["wildcards"][key] for key in shared)


def replay(jobs: list[dict], gpus: int, ranks: dict[str, int]) -> float:
    """Seconds from the first job's start to the last one's end when `jobs` (each run once, for its measured
    seconds) are list-scheduled on `gpus` devices in the rule order `ranks`."""
    needs = [[j for j, other in enumerate(jobs) if depends_on(job, other)] for job in jobs]
    end = [None] * len(jobs)
    free_at = [0.0] * gpus
    started = set()
    clock = 0.0
    while len(started) < len(jobs):
        ready = [i for i in range(len(jobs)) if i not in started
                 and all(end[n] is not None and end[n] <= clock for n in needs[i])]
        for i in [i for i in ready if jobs[i]["device"] is None]:
            started.add(i)
            end[i] = clock + jobs[i]["seconds"]
        gpu_ready = sorted((i for i in ready if jobs[i]["device"] is not None),
                           key=lambda i: (ranks.get(jobs[i]["rule"], 9), i))
        for i in gpu_ready:
            device = min(range(gpus), key=free_at.__getitem__)
            if free_at[device] > clock:
                break
            started.add(i)
            end[i] = free_at[device] = clock + jobs[i]["seconds"]
        pending = [t for t in end if t is not None and t > clock] + [t for t in free_at if t > clock]
        if not pending:
            break
        clock = min(pending)
    return max(end)


def read_smi(path: Path) -> list[tuple[datetime.datetime, str, float, float]]:
    """(time, GPU index, utilisation %, memory MiB) samples, on the job tables' day (they give clock times)."""
    samples = []
    with path.open() as lines:
        for row in csv.reader(lines, skipinitialspace=True):
            if len(row) != 4 or not row[1].strip().isdigit():
                continue
            when = datetime.datetime.strptime(row[0].strip(), "%Y/%m/%d %H:%M:%S.%f").replace(**TABLE_DAY)
            samples.append((when, row[1].strip(), float(row[2].split()[0]), float(row[3].split()[0])))
    return samples


def positive_int(text: str) -> int:
    if not text.isdigit() or int(text) < 1:
        raise argparse.ArgumentTypeError(f"expected a GPU count of at least 1, found {text!r}")
    return int(text)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("tables", type=Path, nargs="+", help="job_timeline.py tables of the run (and its reruns)")
    parser.add_argument("--smi", type=Path, help="nvidia-smi samples of the run")
    parser.add_argument("--gpus", type=positive_int, default=4, metavar="N", help="the machine's GPUs (default 4)")
    parser.add_argument("--plot", type=Path, help="a PNG: every job on its device over time, utilisation behind")
    args = parser.parse_args(argv)
    jobs = read_jobs(args.tables)
    gpu_jobs = [j for j in jobs if j["device"] is not None]
    first, last = min(j["start"] for j in jobs), max(j["end"] or j["start"] for j in jobs)
    window = (min(j["start"] for j in gpu_jobs), max(j["end"] for j in gpu_jobs if j["end"])) if gpu_jobs else None
    wall = (last - first).total_seconds()
    samples = read_smi(args.smi) if args.smi else []

    print("| GPU | jobs | job seconds | share of the GPU window | mean utilisation % (window) | "
          "peak memory MiB |")
    print("|---|---|---|---|---|---|")
    window_s = (window[1] - window[0]).total_seconds() if window else 0.0
    for device in sorted({j["device"] for j in gpu_jobs}):
        mine = [j for j in gpu_jobs if j["device"] == device]
        held = sum(j["seconds"] for j in mine)
        inside = [s for s in samples if s[1] == device and window and window[0] <= s[0] <= window[1]]
        utilisation = f"{sum(s[2] for s in inside) / len(inside):.0f}" if inside else "n/a"
        peak = f"{max(s[3] for s in inside):.0f}" if inside else "n/a"
        share = f"{held / window_s:.0%}" if window_s else "n/a"
        print(f"| {device} | {len(mine)} | {held:.0f} | {share} | {utilisation} | {peak} |")

    if samples:
        print("\n| rule | jobs | mean utilisation % while one held its GPU | samples |")
        print("|---|---|---|---|")
        for rule in sorted({j["rule"] for j in gpu_jobs}):
            held = [s for j in gpu_jobs if j["rule"] == rule and j["end"] for s in samples
                    if s[1] == j["device"] and j["start"] <= s[0] < j["end"]]
            mean = f"{sum(s[2] for s in held) / len(held):.0f}" if held else "n/a"
            print(f"| {rule} | {sum(j['rule'] == rule for j in gpu_jobs)} | {mean} | {len(held)} |")

    done = [j for j in jobs if j["status"] == "done"]
    gpu_sum = sum(j["seconds"] for j in gpu_jobs)
    cpu_sum = sum(j["seconds"] for j in jobs if j["device"] is None)
    print(f"\nwall {wall:.0f} s (first job's start to the last one's end); GPU jobs {gpu_sum:.0f} s summed "
          f"(failed ones included), CPU jobs {cpu_sum:.0f} s; wall / (GPU jobs' sum / {args.gpus} + CPU jobs' sum) "
          f"= {wall / (gpu_sum / args.gpus + cpu_sum):.2f} (1.00: every GPU busy throughout)")
    print(f"wall / every job's sum = {wall / (gpu_sum + cpu_sum):.3f} (ideal on {args.gpus} GPUs: "
          f"{1 / args.gpus:.3f}, if the CPU jobs were free)")
    print(f"\nReplays of the {len(done)} completed jobs with their measured seconds:")
    print("| order | GPUs | wall s |")
    print("|---|---|---|")
    for name, ranks in ORDERS.items():
        for gpus in (args.gpus, 1):
            print(f"| {name} | {gpus} | {replay(done, gpus, ranks):.0f} |")

    if args.plot:
        import matplotlib

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt

        colours = {"fit_avatar": "tab:blue", "render_split": "tab:orange", "evaluate": "tab:green"}
        devices = sorted({j["device"] for j in gpu_jobs})
        figure, axis = plt.subplots(figsize=(10, 1 + 0.8 * len(devices)))
        for row, device in enumerate(devices):
            for job in (j for j in gpu_jobs if j["device"] == device):
                seconds = ((job["end"] or last) - job["start"]).total_seconds()
                axis.barh(row, seconds, left=(job["start"] - first).total_seconds(), height=0.6,
                          color=colours.get(job["rule"], "grey"), edgecolor="black",
                          hatch="//" if job["status"] == "failed" else None)
            mine = [s for s in samples if s[1] == device]
            if mine:
                offsets = [(s[0] - first).total_seconds() for s in mine]
                axis.plot(offsets, [row - 0.4 + 0.8 * s[2] / 100 for s in mine], color="black", linewidth=0.6)
        axis.set_yticks(range(len(devices)), [f"GPU {d}" for d in devices])
        axis.set_xlim(0, wall)
        axis.set_xlabel("seconds since the first job (line: nvidia-smi utilisation; hatched: killed)")
        axis.legend(handles=[matplotlib.patches.Patch(color=c, label=r) for r, c in colours.items()],
                    loc="upper right", fontsize=8)
        figure.tight_layout()
        figure.savefig(args.plot, dpi=100)
        print(f"\nplot: {args.plot}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
