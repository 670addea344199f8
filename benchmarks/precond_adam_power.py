"""What Adam does to Eq. 4's power in the fit: the grid's x-update of each form x optimiser against -eta A^-2 dL/dx.

    python benchmarks/precond_adam_power.py [--iterations 20] [--levels 2 5] [--capture DIR --full --device cuda]
                                            [--set section.key=value ...]

1. A real fit (pig.avatar.training.fit) of the `paper` preset's preconditioning runs `--iterations` steps, observed
   as tests/test_precond_in_fit.py observes it (tests/precond_fit_fixture.py): per step and grid level, dL/dx. By
   default at the tests' CPU sizes on the tests' small synthetic capture (generated here); `--full` keeps the preset's
   own sizes (a GPU and a capture, `--capture`), `--set` overrides keys (fit_gpu.py's short-budget rates, say).
2. "What Adam sees": per level, the size of the gradient each form hands its optimiser (dL/dx without
   preconditioning, A^-1 dL/dx in the substitution form, A^-2 dL/dx in the filter form) against Adam's eps (1e-8),
   and the share of the eps-free step Adam takes: |m / (sqrt(v) + eps)| / |m / sqrt(v)| over the recorded steps.
3. The recorded gradients replayed (open loop, float64, the fit's rates) through none / substitute / filter x adam /
   uniform_adam on each `--levels` level, against Eq. 4's plain steps x - x0 = -sum_t eta A^-2 g_t: the cosine of the
   two updates; the effective power p, fitted over every mode of the 3-D DCT as |dx^| / |G^| ~ (1 + lambda mu)^-p
   with G = sum_t eta g_t (Eq. 4: p = 2; no filter: p = 0); and its RMS against substitute + adam's (the rate
   multiplier that would match it). Eps 1e-15 rows: the candidate lever precond.adam_eps.
"""
from __future__ import annotations

import argparse
import sys
import tempfile
from pathlib import Path

import numpy as np
import torch
import yaml

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests"))

from precond_fit_fixture import observe_fit, paper_test_preset  # noqa: E402

from pig.config import load_preset  # noqa: E402
from pig.field.lattice_solve import LatticeSystem, dct_matrix, path_laplacian_eigenvalues  # noqa: E402

EPS, BETA1, BETA2 = 1e-8, 0.9, 0.999
# (form, optimiser, Adam's eps): the preset's (substitute, adam, 1e-8) and the alternatives, eps 1e-15 being the
# candidate lever precond.adam_eps (Adam without eps's damping at these gradient sizes).
COMBINATIONS = [("none", "adam", EPS), ("substitute", "adam", EPS), ("filter", "adam", EPS), ("filter", "uniform_adam", EPS),
                ("substitute", "uniform_adam", EPS), ("none", "adam", 1e-15), ("substitute", "adam", 1e-15),
                ("filter", "uniform_adam", 1e-15)]


def small_capture(root: Path) -> Path:
    """The tests' small capture (tests/conftest.py: 5 cameras x 4 frames at 48 px)."""
    from pig.data.synthetic import SyntheticConfig, generate_capture
    from pig.stages.preprocess import main as preprocess

    raw = generate_capture(root / "raw", SyntheticConfig(cameras=5, frames=4, width=48, height=48, workers=1), progress=False)
    preprocess(["--input", str(raw), "--output", str(root / "capture"), "--preset", "test", "--format", "thuman4",
                "--body-model", str(raw / "body_model.npz"), "--no-progress"])
    return root / "capture"


def full_preset(path: Path, iterations: int, overrides: dict) -> str:
    preset = load_preset("paper")
    preset.pop("_path")
    preset["fit"].update(iterations=iterations, weight_lpips=0.0, eval_every=10**6)
    for section, values in overrides.items():
        preset[section].update(values)
    path.write_text(yaml.safe_dump(preset))
    return str(path)


class AdamStep:
    """Adam (uniform: one second moment per tensor) in float64, fed one gradient at a time: its summed step, and
    per step the share of the eps-free step |m^ / (sqrt(v^) + eps)| / |m^ / sqrt(v^)| that it took."""

    def __init__(self, uniform: bool, eps: float = EPS):
        self.uniform, self.eps, self.t, self.m, self.v, self.total, self.shares = uniform, eps, 0, 0.0, 0.0, 0.0, []

    def __call__(self, g: np.ndarray, lr: float) -> None:
        self.t += 1
        self.m = BETA1 * self.m + (1 - BETA1) * g
        self.v = BETA2 * self.v + (1 - BETA2) * (np.max(g**2) if self.uniform else g**2)
        mh, root = self.m / (1 - BETA1**self.t), np.sqrt(self.v / (1 - BETA2**self.t))
        step = mh / (root + self.eps)
        ideal = np.divide(mh, root, out=np.zeros_like(mh), where=np.broadcast_to(root, mh.shape) > 0)
        self.shares.append(float(np.abs(step).sum() / max(np.abs(ideal).sum(), 1e-300)))
        self.total = self.total - lr * step


def dct3(x: np.ndarray) -> np.ndarray:
    """Orthonormal 3-D DCT-II of (C, n, n, n) over its last three axes."""
    c = dct_matrix(x.shape[-1]).numpy()
    return np.einsum("dk,cabk->cabd", c, np.einsum("bj,cajk->cabk", c, np.einsum("ai,cijk->cajk", c, x)))


def effective_power(update: np.ndarray, drive: np.ndarray, lam: float) -> float:
    """p of |dx^| / |G^| ~ c (1 + lambda mu)^-p, fitted over every DCT mode and channel by least squares in logs,
    weighted by the drive's energy |G^|^2 (Eq. 4's plain steps: exactly 2; an unfiltered step: ~0)."""
    n = update.shape[-1]
    mu1 = path_laplacian_eigenvalues(n).numpy()
    level = np.broadcast_to(np.log1p(lam * (mu1[:, None, None] + mu1[None, :, None] + mu1[None, None, :])), update.shape)
    u, d = np.abs(dct3(update)), np.abs(dct3(drive))
    keep = (u > 0) & (d > 1e-12 * d.max())
    x, y, w = level[keep], np.log(u[keep] / d[keep]), d[keep] ** 2
    slope = np.polyfit(x, y, 1, w=np.sqrt(w))[0]
    return float(-slope)


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--iterations", type=int, default=20)
    parser.add_argument("--levels", type=int, nargs="+", default=[2, 5], help="grid levels replayed (0 coarsest)")
    parser.add_argument("--capture", type=Path, default=None, help="a preprocessed capture (default: the tests' small one)")
    parser.add_argument("--full", action="store_true", help="the paper preset's own sizes (else the tests' CPU sizes)")
    parser.add_argument("--device", default="cpu")
    parser.add_argument("--set", action="append", default=[], help="section.key=value over the preset (repeatable)")
    args = parser.parse_args(argv)
    overrides: dict[str, dict] = {}
    for item in args.set:
        key, value = item.split("=", 1)
        section, name = key.split(".", 1)
        overrides.setdefault(section, {})[name] = yaml.safe_load(value)

    with tempfile.TemporaryDirectory() as tmp:
        root = Path(tmp)
        capture = args.capture or small_capture(root)
        if args.full:
            preset = full_preset(root / "preset.yaml", args.iterations, overrides)
        else:
            preset = paper_test_preset(root / "preset.yaml", args.iterations, overrides.get("precond"))
        record = observe_fit(capture, root / "fit", preset, "pig", device=args.device, gradients_only=True)
    levels = list(record.model.grid.levels)
    print(f"\n{len(record.steps)} steps of the fit ({'paper sizes' if args.full else 'test sizes'}; "
          f"grid {[tuple(l.param.shape[1:])[0] for l in levels]}), Adam eps {EPS:g}\n")

    print("What each form hands its optimiser (values at the last step), and the share of Adam's eps-free step taken")
    print("| level | n | lambda | form | median abs | 99th pct abs | max abs | share of elements > eps | Adam step / eps-free, first | last |")
    print("|---|---|---|---|---|---|---|---|---|---|")
    replay = {}
    for g, level in enumerate(levels):
        system = LatticeSystem(level.system.shape, level.system.lam)
        solve = lambda x: system.solve(torch.as_tensor(x, dtype=torch.float64)).numpy()  # noqa: E731
        raw = [step["dx"].pop(f"grid{g}").numpy() for step in record.steps]
        lrs = [step["lr"][f"grid{g}"] for step in record.steps]
        forms = {"none: dL/dx": 0, "substitute: A^-1 dL/dx": 1, "filter: A^-2 dL/dx": 2}
        adams = {form: AdamStep(uniform=False) for form in forms}
        for x, lr in zip(raw, lrs):
            seen = {0: x.astype(np.float64)}
            seen[1] = solve(seen[0])
            seen[2] = solve(seen[1])
            for form, power in forms.items():
                adams[form](seen[power], lr)
        for form, power in forms.items():
            values = np.abs(seen[power])
            shares = adams[form].shares
            print(f"| {g} | {system.shape[0]} | {system.lam:.3g} | {form} | {np.median(values):.2e} | "
                  f"{np.quantile(values, 0.99):.2e} | {values.max():.2e} | {(values > EPS).mean():.3f} | "
                  f"{shares[0]:.3f} | {shares[-1]:.3f} |")
        if g in args.levels:
            replay[g] = (system, solve, raw, lrs)

    print("\nThe recorded gradients replayed through each form x optimiser, against Eq. 4's plain steps")
    print("| level | form | optimiser | eps | cosine with Eq. 4 | effective power p | RMS / substitute+adam's |")
    print("|---|---|---|---|---|---|---|")
    for g, (system, solve, raw, lrs) in replay.items():
        drive = -sum(lr * x.astype(np.float64) for lr, x in zip(lrs, raw))
        eq4 = solve(solve(drive))
        adams = {(form, kind, eps): AdamStep(kind == "uniform_adam", eps) for form, kind, eps in COMBINATIONS}
        for x, lr in zip(raw, lrs):
            once = solve(x.astype(np.float64))
            twice = solve(once)
            for (form, kind, eps), adam in adams.items():
                adam({"none": x.astype(np.float64), "substitute": once, "filter": twice}[form], lr)
        updates = {("Eq. 4", "sgd", None): eq4}
        for (form, kind, eps), adam in adams.items():
            updates[(form, kind, eps)] = solve(adam.total) if form == "substitute" else adam.total
        reference_rms = np.sqrt(np.mean(updates[("substitute", "adam", EPS)] ** 2))
        for (form, kind, eps), dx in updates.items():
            cosine = float((dx * eq4).sum() / (np.linalg.norm(dx) * np.linalg.norm(eq4)))
            print(f"| {g} | {form} | {kind} | {'-' if eps is None else f'{eps:g}'} | {cosine:.3f} | "
                  f"{effective_power(dx, drive, system.lam):.2f} | {np.sqrt(np.mean(dx**2)) / reference_rms:.3g} |")


if __name__ == "__main__":
    main()
