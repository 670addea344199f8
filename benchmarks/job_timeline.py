"""The jobs of one Snakemake run as a table: rule, wildcards, start, end, seconds, and the GPU each one held.

    python benchmarks/job_timeline.py SNAKEMAKE_OUTPUT [--workdir DIR]

Reads Snakemake's own output (the terminal's or .snakemake/log/*.snakemake.log; `[date]` before each job's start,
`Finished jobid: N` at its end) and, from each job's `log:` file (relative to --workdir), the line in which the
GPU slot launcher (pig.gpu_slots) names the job's CUDA_VISIBLE_DEVICES and when it got it. Prints Markdown.
"""
from __future__ import annotations

import argparse
import datetime
import re
from pathlib import Path

STAMP = re.compile(r"^\[(\w{3} \w{3} +\d+ \d\d:\d\d:\d\d \d{4})\]$")
SLOT = re.compile(r"^(\S+) \S+: GPU slot\(s\) held, CUDA_VISIBLE_DEVICES=(\S+)")


def parse(text: str) -> dict[int, dict]:
    """{jobid: {rule, wildcards, log, start, end, status}} from Snakemake's output."""
    jobs: dict[int, dict] = {}
    stamp, current = None, None
    for line in text.splitlines():
        if found := STAMP.match(line.strip()):
            stamp, current = datetime.datetime.strptime(found.group(1), "%a %b %d %H:%M:%S %Y"), None
            continue
        if found := re.match(r"^(?:local)?rule (\w+):$", line):
            current = {"rule": found.group(1), "start": stamp, "wildcards": "", "log": None, "end": None,
                       "status": "running"}
        elif "rule" in (current or {}) and (found := re.match(r"^\s+(jobid|wildcards|log): (.*)$", line)):
            key, value = found.groups()
            if key == "jobid":
                jobs[int(value)] = current
            else:
                current[key] = value.split(" (check log")[0]
        elif found := re.match(r"^Finished jobid: (\d+)", line):
            if int(found.group(1)) in jobs:
                jobs[int(found.group(1))].update(end=stamp, status="done")
        elif found := re.match(r"^Error in rule (\w+):", line):
            current = {"error": True}
        elif current is not None and current.get("error") and (found := re.match(r"^\s+jobid: (\d+)", line)):
            if int(found.group(1)) in jobs:
                jobs[int(found.group(1))].update(end=stamp, status="failed")
    return jobs


def slot_line(log: Path) -> tuple[str, str]:
    """(when the slot was held, CUDA_VISIBLE_DEVICES) from a job's log; ("", "-") for a job that took none."""
    if log.is_file():
        with log.open(errors="replace") as lines:
            for line in lines:
                if found := SLOT.match(line):
                    return found.group(1)[11:23], found.group(2)
    return "", "-"


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("output", type=Path, help="Snakemake's output of the run")
    parser.add_argument("--workdir", type=Path, default=Path("."), help="the run's working directory (logs)")
    args = parser.parse_args(argv)
    jobs = parse(args.output.read_text(errors="replace"))
    print("| job | rule | wildcards | start | end | s | status | slot held (UTC) | CUDA_VISIBLE_DEVICES |")
    print("|---|---|---|---|---|---|---|---|---|")
    for jobid, job in sorted(jobs.items(), key=lambda item: (item[1]["start"], item[0])):
        held, device = slot_line(args.workdir / job["log"]) if job["log"] else ("", "-")
        seconds = f"{(job['end'] - job['start']).total_seconds():.0f}" if job["end"] else ""
        end = job["end"].strftime("%H:%M:%S") if job["end"] else ""
        print(f"| {jobid} | {job['rule']} | {job['wildcards']} | {job['start']:%H:%M:%S} | {end} | {seconds} | "
              f"{job['status']} | {held} | {device} |")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
