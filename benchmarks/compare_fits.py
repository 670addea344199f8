"""Run-to-run spread of identical fits: their avatar.pt tensors against the first fit's, and their held-out PSNR.

For fit folders (each with avatar.pt and train_log.csv) of the same capture, preset and seed: per folder, how many
of the avatar's tensors differ from the first folder's and by how much at most, and the last held-out PSNR of its
train log; then the spread (max - min, standard deviation) of that PSNR. Bit-identical fits show 0 tensors differing.

    python benchmarks/compare_fits.py /tmp/fb/fit_nd_a /tmp/fb/fit_nd_b /tmp/fb/fit_nd_c [--json out.json]
"""
from __future__ import annotations

import argparse
import csv
import json
import statistics
import sys
from pathlib import Path

import torch


def last_heldout(log: Path) -> tuple[int, float]:
    """(iteration, held-out PSNR) of the last train-log row that has one."""
    with open(log, newline="") as file:
        rows = [r for r in csv.DictReader(file) if r.get("heldout_psnr")]
    if not rows:
        raise SystemExit(f"{log}: no row with a held-out PSNR (expected a fit's train_log.csv)")
    return int(rows[-1]["iteration"]), float(rows[-1]["heldout_psnr"])


def compare(folders: list[Path]) -> dict:
    for folder in folders:
        for name in ("avatar.pt", "train_log.csv"):
            if not (folder / name).is_file():
                raise SystemExit(f"{folder}: no {name} (expected a finished fit's folder)")
    first = torch.load(folders[0] / "avatar.pt", weights_only=True)["model"]
    rows = []
    for folder in folders:
        model = torch.load(folder / "avatar.pt", weights_only=True)["model"]
        if model.keys() != first.keys():
            raise SystemExit(f"{folder}/avatar.pt: other tensors than {folders[0]}/avatar.pt (another model)")
        differ = {k: (model[k].double() - first[k].double()).abs().max().item() for k in first
                  if not torch.equal(model[k], first[k])}
        iteration, psnr = last_heldout(folder / "train_log.csv")
        rows.append({"fit": str(folder), "tensors": len(first), "tensors_differing": len(differ),
                     "max_abs_diff": max(differ.values(), default=0.0), "iteration": iteration, "heldout_psnr": psnr})
    values = [r["heldout_psnr"] for r in rows]
    return {"fits": rows, "psnr_spread_db": max(values) - min(values),
            "psnr_std_db": statistics.stdev(values) if len(values) > 1 else 0.0}


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("folders", type=Path, nargs="+", help="fit output folders; the first is the reference")
    parser.add_argument("--json", type=Path, default=None, help="also write the result here")
    args = parser.parse_args(argv)
    result = compare(args.folders)
    print("| fit | tensors differing from the first | max abs difference | iteration | held-out PSNR dB |\n"
          "|---|---|---|---|---|")
    for r in result["fits"]:
        print(f"| {r['fit']} | {r['tensors_differing']} of {r['tensors']} | {r['max_abs_diff']:.3g} | {r['iteration']} | "
              f"{r['heldout_psnr']:.4f} |")
    print(f"\nheld-out PSNR spread (max - min) {result['psnr_spread_db']:.4f} dB, standard deviation "
          f"{result['psnr_std_db']:.4f} dB over {len(result['fits'])} fits")
    if args.json is not None:
        args.json.write_text(json.dumps(result, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
