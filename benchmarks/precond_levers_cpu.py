"""Equal-iteration fits of the cpu-demo preset with preconditioner levers, one after another on one thread.

    PYTHONPATH=$PWD python benchmarks/precond_levers_cpu.py --capture results/synthetic/subject00/capture \\
        --out /tmp/levers --variant pig: --variant pig_uniform:precond.form=filter,precond.optimizer=uniform_adam

A variant is `NAME:section.key=value,...` as in fit_gpu.py; NAME's part before the first `_` that names a preset
variant (`pig`, `no_precond`, ...) picks the method variant. Prints per variant the iterations, training seconds and
the final held-out PSNR and the probes' (fit.probe_every) along the way. CPU scale: it decides nothing about a GPU fit.
"""
from __future__ import annotations

import argparse
import csv
import sys
from pathlib import Path

import yaml

sys.path.insert(0, str(Path(__file__).resolve().parent))

from fit_gpu import parse_variant  # noqa: E402

from pig.avatar.training import fit  # noqa: E402
from pig.config import load_preset  # noqa: E402


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--capture", type=Path, required=True)
    parser.add_argument("--out", type=Path, required=True, help="a new folder for the fits")
    parser.add_argument("--preset", default="cpu-demo")
    parser.add_argument("--threads", type=int, default=1)
    parser.add_argument("--variant", action="append", required=True, help="NAME:section.key=value,... (repeatable)")
    args = parser.parse_args(argv)
    args.out.mkdir(parents=True, exist_ok=False)
    rows = []
    for text in args.variant:
        name, overrides = parse_variant(text)
        preset = load_preset(args.preset)
        preset.pop("_path")
        for section, values in overrides.items():
            preset[section].update(values)
        path = args.out / f"{name}.yaml"
        path.write_text(yaml.safe_dump(preset))
        method = name.split("_")[0] if name.split("_")[0] in preset["variants"] else name
        method = method if method in preset["variants"] else "pig"
        fit(args.capture, args.out / name, str(path), variant=method, threads=args.threads)
        with open(args.out / name / "train_log.csv", newline="") as file:
            log = list(csv.DictReader(file))
        last = [r for r in log if r["heldout_psnr"]][-1]
        rows.append((name, method, overrides, log, last))
        print(f"variant {name}: {last['iteration']} iterations, {float(last['train_s']):.0f} training s, "
              f"held-out PSNR {float(last['heldout_psnr']):.2f} dB", flush=True)
    print("\n| variant | method | overrides | iterations | training s | held-out PSNR | probe PSNR by iteration |")
    print("|---|---|---|---|---|---|---|")
    for name, method, overrides, log, last in rows:
        over = ", ".join(f"{s}.{k}={v}" for s, kv in overrides.items() for k, v in kv.items()) or "-"
        curve = " ".join(f"{r['iteration']}: {float(r['probe_psnr']):.2f}" for r in log if r.get("probe_psnr"))
        print(f"| {name} | {method} | {over} | {last['iteration']} | {float(last['train_s']):.0f} | "
              f"{float(last['heldout_psnr']):.2f} | {curve} |")


if __name__ == "__main__":
    main()
