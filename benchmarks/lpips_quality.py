"""What Eq. 15's LPIPS term buys at equal training time: two fits of one capture, with and without the term.

For the first user with the real LPIPS weights (torchvision's vgg16-397923af.pth and the lpips package's vgg.pth
in the torch hub cache; these machines have none): each fit trains for `--budget` seconds (`fit.time_budget_s`;
held-out evaluations not counted), then the render and evaluate stages score novel view and novel pose at every
LOD, and one table per fit is printed (PSNR, SSIM, LPIPS per split and LOD) and a last one of the differences.
With the term on, each iteration costs more, so the fit with it makes fewer iterations: the question is whether
they are worth it. `--set section.key=value,...` changes the preset for both fits (e.g. `fit.lpips_form=full`);
`--lpips-weights random` runs the same command where the weights are absent (its numbers mean nothing: a check
of the command itself). Example, on a GPU with a capture made by `benchmarks/fit_gpu.py --capture-only`:

    python3 benchmarks/lpips_quality.py --capture /tmp/pig_fit_bench/capture --budget 1800 --workdir /tmp/lq
"""
from __future__ import annotations

import argparse
import math
import sys
from pathlib import Path

import yaml

sys.path.insert(0, str(Path(__file__).resolve().parent))
from fit_gpu import evaluate_budget_run, parse_variant  # noqa: E402

from pig.avatar.checkpoint import loss_terms  # noqa: E402
from pig.avatar.training import fit  # noqa: E402
from pig.config import load_preset  # noqa: E402

METRICS = ("psnr", "ssim", "lpips")


def _number(value) -> float:
    """A metric of a summary; missing (absent weights: null in the strict JSON) as NaN."""
    return math.nan if value is None else float(value)


def table(title: str, rows: dict[tuple[str, int], dict]) -> str:
    lines = [title, "| split | LOD | images | " + " | ".join(METRICS) + " |", "|---|---|---|" + "---|" * len(METRICS)]
    for (split, lod), values in sorted(rows.items()):
        cells = " | ".join(f"{_number(values.get(m)):.4f}" for m in METRICS)
        lines.append(f"| {split} | {lod} | {values.get('images', '')} | {cells} |")
    return "\n".join(lines)


def scores(result: dict) -> dict[tuple[str, int], dict]:
    return {(split, lod): values for split in ("novel_view", "novel_pose") for lod, values in result[split].items()}


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--capture", type=Path, required=True, help="a preprocessed capture folder")
    parser.add_argument("--workdir", type=Path, required=True, help="fits, renders and metrics go here")
    parser.add_argument("--preset", default="paper")
    parser.add_argument("--budget", type=float, required=True, help="seconds of training per fit")
    parser.add_argument("--device", default="auto")
    parser.add_argument("--lpips-weights", choices=("pretrained", "random"), default="pretrained")
    parser.add_argument("--set", default="", help="section.key=value,... over the preset, for both fits")
    parser.add_argument("--finest-only", action="store_true", help="evaluate the finest LOD only")
    args = parser.parse_args(argv)

    preset = load_preset(args.preset)
    preset.pop("_path")
    for section, values in parse_variant(f"set:{args.set}")[1].items():
        preset.setdefault(section, {}).update(values)
    args.workdir.mkdir(parents=True, exist_ok=True)
    results = {}
    for name, weight in (("with_lpips", preset["fit"].get("weight_lpips", 2.0) or 2.0), ("without_lpips", 0.0)):
        varied = yaml.safe_load(yaml.safe_dump(preset))
        varied["fit"].update(weight_lpips=weight, lpips_weights=args.lpips_weights, iterations=10**7, time_budget_s=args.budget)
        path = args.workdir / f"preset_{name}.yaml"
        path.write_text(yaml.safe_dump(varied))
        fit_dir = args.workdir / f"fit_{name}"
        avatar = fit(args.capture, fit_dir, str(path), device=args.device, overwrite=True)
        results[name] = evaluate_budget_run(args, name, fit_dir, path, args.capture)
        results[name]["term"] = loss_terms(avatar)["lpips"]["state"]

    settings = f" + {args.set}" if args.set else ""
    print(f"capture {args.capture}, preset {args.preset}{settings}, {args.budget:g} s of training each")
    for name, result in results.items():
        print("\n" + table(f"{name}: {result['iterations']} iterations, LPIPS term {result['term']!r}", scores(result)))
    on, off = scores(results["with_lpips"]), scores(results["without_lpips"])
    diff = {key: {m: _number(on[key].get(m)) - _number(off[key].get(m)) for m in METRICS} for key in on if key in off}
    print("\n" + table("with_lpips - without_lpips", diff))
    return 0


if __name__ == "__main__":
    sys.exit(main())
