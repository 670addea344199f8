"""benchmarks/parity.py --path: repeated runs of a path pooled into a mean and a spread per evaluation."""
import json
import re
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

SCRIPT = Path(__file__).resolve().parents[1] / "benchmarks" / "parity.py"


def write_runs(path: Path, curves: dict[str, dict[int, float]]) -> Path:
    path.write_text(json.dumps({"results": [{"name": name, "heldout": {str(k): v for k, v in curve.items()},
                                             "heldout_by_time": []} for name, curve in curves.items()]}))
    return path


def run(*args) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, str(SCRIPT), *map(str, args)], capture_output=True, text=True)


def test_pooled_means_and_spreads_match_numpy(tmp_path):
    rng = np.random.default_rng(0)
    steps = [0, 250, 500]
    curves = {name: dict(zip(steps, rng.normal(30, 1, 3).round(3).tolist())) for name in ("ref_a", "ref_b", "ref_c", "new_a", "new_b")}
    # new_c lacks step 500: the pooled table keeps only the evaluations every run has
    curves["new_c"] = {0: 29.0, 250: 31.0}
    result = run(write_runs(tmp_path / "r.json", curves), "--path", "ref=ref_a,ref_b,ref_c", "--path", "new=new_a,new_b,new_c")
    assert result.returncode == 0, result.stderr
    rows = {int(m.group(1)): [float(x) for x in m.group(2).split(" | ")]
            for m in re.finditer(r"^\| (\d+) \| ([-+0-9. |]+) \|$", result.stdout.split("ref mean")[1], re.M)}
    assert sorted(rows) == [0, 250]
    for step, (ref_mean, new_mean, difference, ref_spread, new_spread) in rows.items():
        ref = [curves[n][step] for n in ("ref_a", "ref_b", "ref_c")]
        new = [curves[n][step] for n in ("new_a", "new_b", "new_c")]
        assert ref_mean == pytest.approx(np.mean(ref), abs=5e-4) and new_mean == pytest.approx(np.mean(new), abs=5e-4)
        assert difference == pytest.approx(np.mean(new) - np.mean(ref), abs=1e-3)
        assert ref_spread == pytest.approx(np.ptp(ref), abs=5e-4) and new_spread == pytest.approx(np.ptp(new), abs=5e-4)
    worst = max(abs(np.mean([curves[n][s] for n in ("new_a", "new_b", "new_c")]) -
                    np.mean([curves[n][s] for n in ("ref_a", "ref_b", "ref_c")])) for s in (0, 250))
    assert f"largest |new - ref| of the means: {worst:.3f} dB" in result.stdout


def test_unknown_run_is_named(tmp_path):
    file = write_runs(tmp_path / "r.json", {"a": {0: 1.0}, "b": {0: 2.0}})
    result = run(file, "--path", "x=a", "--path", "y=b,c")
    assert result.returncode != 0 and "['c']" in result.stderr and "['a', 'b']" in result.stderr
