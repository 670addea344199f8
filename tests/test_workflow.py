"""The Snakemake workflow's rerun rules and shell quoting, through real `snakemake` runs.

Most tests work on a fake THuman4 subject whose outputs all exist and are recorded as up to date
(`--touch`), in a folder whose path, raw data, preset, dataset YAML and subject name hold spaces, and
assert which jobs a dry run schedules after one change: a preset value, the dataset split, a raw image
or mask, `avatar.levels`. Snakemake runs in a fresh interpreter (snakemake_exit: a fork of the test process,
~1 s faster a dry run, hung or crashed in the child where the process had run torch). Building the DAG imports
no torch (a test checks it in a fresh interpreter).
"""
from __future__ import annotations

import multiprocessing
import os
import shlex
import shutil
import subprocess
import sys
from pathlib import Path

import pytest
import snakemake.cli
import yaml

import pig.data.formats  # noqa: F401  (imported by the workflow at DAG time; loaded once here for a forked run)
import pig.data.synthetic.config  # noqa: F401
from pig.stages.evaluate import EvaluateConfig, evaluate_split

REPO = Path(__file__).resolve().parent.parent
SUBJECT = "subject 00"
TARGET = "results/tables/thuman4.csv"
PRESET = "config/test preset.yaml"
DATASET = "config/data sets/thuman4.yaml"
# Jobs of TARGET (2 held-out splits, each evaluated at its 2 LODs in one job) from each stage on.
FROM_PREPROCESS = {"preprocess_capture": 1, "fit_avatar": 1, "render_split": 2, "evaluate": 2, "make_tables": 1}
FROM_FIT = {rule: n for rule, n in FROM_PREPROCESS.items() if rule != "preprocess_capture"}
FROM_RENDER = {rule: n for rule, n in FROM_FIT.items() if rule != "fit_avatar"}


def _snakemake_child(argv: list[str], log: Path) -> None:
    stream = open(log, "w", buffering=1)
    os.dup2(stream.fileno(), 1)
    os.dup2(stream.fileno(), 2)
    sys.stdout = sys.stderr = stream  # pytest's capture objects would otherwise get Snakemake's log
    # The rules' `python -m pig STAGE` commands must import this checkout's package.
    os.environ["PYTHONPATH"] = os.pathsep.join(filter(None, [str(REPO), os.environ.get("PYTHONPATH")]))
    snakemake.cli.main(argv)


def snakemake_exit(workdir: Path, *args: str, fork: bool = False) -> tuple[int, str]:
    """(exit code, output) of `snakemake ARGS` on the workflow in `workdir`, in a fresh interpreter. `fork`: in a
    forked child of this process instead, which sees this process's monkeypatches (for a test that patches what the
    workflow checks while it builds its DAG). Forks are otherwise avoided: a fork of a test process that has run
    torch (its thread pools, tqdm's monitor thread) hung or crashed in the child in CI (2026-11-27: SIGSEGV before a
    line, a hang after the first, a hang inside an import), as a fork of a process with running threads may."""
    argv = [*args, "--snakefile", str(REPO / "Snakefile"), "--directory", str(workdir)]
    if fork:
        log = workdir.parent / "snakemake.out"
        child = multiprocessing.get_context("fork").Process(target=_snakemake_child, args=(argv, log))
        child.start()
        child.join(timeout=300)
        if child.is_alive():
            child.kill()
            child.join()
        return child.exitcode, log.read_text()
    # The rules' `python -m pig STAGE` commands must import this checkout's package.
    env = dict(os.environ, PYTHONPATH=os.pathsep.join(filter(None, [str(REPO), os.environ.get("PYTHONPATH")])))
    try:
        done = subprocess.run([sys.executable, "-m", "snakemake", *argv], stdout=subprocess.PIPE,
                              stderr=subprocess.STDOUT, text=True, env=env, timeout=300)
    except subprocess.TimeoutExpired as err:  # its output arrives as bytes, whatever `text` says
        return -9, err.output.decode(errors="replace") if isinstance(err.output, bytes) else (err.output or "")
    return done.returncode, done.stdout


def snakemake_run(workdir: Path, *args: str) -> str:
    """Output of `snakemake ARGS` on the workflow in `workdir` (snakemake_exit); fails the test when Snakemake fails."""
    code, output = snakemake_exit(workdir, *args)
    assert code == 0, f"snakemake {' '.join(args)} exited {code}:\n{output[-5000:]}"
    return output


def scheduled(workdir: Path, target: str = TARGET) -> dict[str, int]:
    """{rule: jobs} that a dry run of `target` schedules; {} when everything is up to date."""
    output = snakemake_run(workdir, target, "--dry-run", "--quiet", "rules")
    if "Nothing to be done" in output:
        return {}
    return job_counts(output)


def job_counts(output: str) -> dict[str, int]:
    """{rule: jobs} of the "Job stats" table in Snakemake's output."""
    assert "Job stats:" in output, output[-3000:]
    counts = {}
    for line in output.split("Job stats:", 1)[1].splitlines()[3:]:
        rule, count = line.split()
        if rule == "total":
            return counts
        counts[rule] = int(count)
    raise AssertionError(f"no job total in:\n{output[-3000:]}")


def edit_yaml(path: Path, change) -> str:
    """Apply `change` to the mapping in `path`; returns the old text."""
    text = path.read_text()
    data = yaml.safe_load(text)
    change(data)
    path.write_text(yaml.safe_dump(data))
    return text


def _fake_thuman4_subject(root: Path) -> None:
    """Files in the THuman4 layout: the DAG only checks they exist, nothing reads them in a dry run."""
    for kind in ("images", "masks"):
        for cam in ("cam00", "cam01"):
            (root / kind / cam).mkdir(parents=True)
            for frame in range(2):
                (root / kind / cam / f"{frame:08d}.jpg").write_bytes(b"frame")
    (root / "calibration.json").write_text("{}")
    (root / "smpl_params.npz").write_bytes(b"params")


def _workflow_config(work: Path, dataset: str) -> None:
    """config/ of the repository, with the test preset and the thuman4 dataset YAML at paths with spaces."""
    shutil.copytree(REPO / "config", work / "config")
    shutil.copyfile(REPO / "config" / "presets" / "test.yaml", work / PRESET)
    (work / DATASET).parent.mkdir()
    thuman4 = yaml.safe_load((REPO / "config" / "datasets" / "thuman4.yaml").read_text())
    thuman4.update(root="raw data", body_model="raw data/SMPLX NEUTRAL.npz", subjects=[SUBJECT])
    (work / DATASET).write_text(yaml.safe_dump(thuman4))
    config = yaml.safe_load((REPO / "config" / "config.yaml").read_text())
    config.update(preset=PRESET, dataset=dataset)
    config["datasets"]["thuman4"] = DATASET
    (work / "config" / "config.yaml").write_text(yaml.safe_dump(config))


@pytest.fixture(scope="module")
def recorded(tmp_path_factory) -> Path:
    """A workflow folder whose every output of TARGET exists (empty) and is recorded as up to date."""
    work = tmp_path_factory.mktemp("workflow") / "work dir"
    _workflow_config(work, "thuman4")
    _fake_thuman4_subject(work / "raw data" / SUBJECT)
    (work / "raw data" / "SMPLX NEUTRAL.npz").write_bytes(b"model")
    for line in snakemake_run(work, TARGET, "--summary").splitlines():
        fields = line.split("\t")
        if len(fields) < 5 or fields[0] == "output_file":
            continue
        path = work / fields[0]
        if fields[2] == "render_split":  # directory() outputs
            path.mkdir(parents=True)
        else:
            path.parent.mkdir(parents=True, exist_ok=True)
            path.touch()
    snakemake_run(work, TARGET, "--touch", "--forceall", "--cores", "1")
    return work


@pytest.fixture
def workflow(recorded, tmp_path) -> Path:
    """A copy of `recorded` (mtimes and Snakemake's metadata included) that a test may change."""
    work = tmp_path / "work dir"
    shutil.copytree(recorded, work, symlinks=True)
    assert scheduled(work) == {}
    return work


def test_shell_commands_quote_every_path(recorded):
    output = snakemake_run(recorded, TARGET, "--dry-run", "--printshellcmds", "--forceall")
    # Snakemake finds workflow/profiles/default as profiles/default (a link) beside the Snakefile.
    used = output.split("Using workflow specific profile ", 1)[1].split(" for setting", 1)[0]
    assert Path(used).resolve() == REPO / "workflow" / "profiles" / "default"
    commands = [line.split("Shell command: ", 1)[1] for line in output.splitlines() if "Shell command: " in line]
    assert len(commands) == sum(FROM_PREPROCESS.values())
    for command in commands:
        words = shlex.split(command)
        # Every path of this workflow but the tables folder holds a space; an unquoted one splits in two.
        paths = [w for w in words if "/" in w]
        assert paths and all(" " in p or p.startswith("results/tables") for p in paths), command
        if "python -m pig tables " not in command:
            assert words[words.index("--preset") + 1] == PRESET, command
    preprocess = shlex.split(next(c for c in commands if "python -m pig preprocess " in c))
    values = dict(zip(preprocess, preprocess[1:]))
    assert values["--input"] == f"raw data/{SUBJECT}"
    assert values["--body-model"] == "raw data/SMPLX NEUTRAL.npz"
    assert values["--dataset"] == DATASET
    assert values["--subject"] == SUBJECT
    assert values[">"] == f"results/thuman4/{SUBJECT}/logs/preprocess.log"


def test_preset_change_reruns_the_stages_that_read_it(workflow):
    preset = workflow / PRESET
    original = edit_yaml(preset, lambda p: p["fit"].update(iterations=41))
    assert scheduled(workflow) == FROM_FIT
    preset.write_text(original)
    edit_yaml(preset, lambda p: p["evaluate"].update(batch_size=3))  # read by render and evaluate
    assert scheduled(workflow) == FROM_RENDER
    preset.write_text(original)
    # Sections no stage of TARGET reads: another variant's overrides, the synthetic generator.
    edit_yaml(preset, lambda p: (p["variants"]["no_offsets"].update(avatar={"offsets": True}),
                                  p["synthetic"].update(frames=9)))
    assert scheduled(workflow) == {}


def test_avatar_levels_change_rebuilds_fit_render_evaluate_tables(workflow):
    edit_yaml(workflow / PRESET, lambda p: p["avatar"].update(levels=3))
    assert scheduled(workflow) == FROM_FIT  # one evaluate job per split, whatever its LODs


def test_dataset_split_change_reruns_preprocess(workflow):
    dataset = workflow / DATASET
    original = edit_yaml(dataset, lambda d: d["split"].update(novel_view_cameras=["cam01"]))
    assert scheduled(workflow) == FROM_PREPROCESS
    dataset.write_text(original)
    edit_yaml(dataset, lambda d: d.update(subjects=[SUBJECT, "subject01"]))  # other subjects do not count
    assert scheduled(workflow, f"results/thuman4/{SUBJECT}/capture/report.json") == {}


def test_raw_image_rewritten_with_its_old_mtime_reruns_preprocess(workflow):
    image = workflow / "raw data" / SUBJECT / "images" / "cam01" / "00000001.jpg"
    stat = image.stat()
    image.write_bytes(b"frame!")
    os.utime(image, ns=(stat.st_atime_ns, stat.st_mtime_ns))  # as `cp -p` or `rsync -t` leave it
    assert scheduled(workflow) == FROM_PREPROCESS


def test_raw_mask_replaced_by_an_older_file_reruns_preprocess(workflow):
    mask = workflow / "raw data" / SUBJECT / "masks" / "cam00" / "00000000.jpg"
    stat = mask.stat()
    os.utime(mask, ns=(stat.st_atime_ns, stat.st_mtime_ns - 3600 * 10**9))  # older than every output
    assert scheduled(workflow) == FROM_PREPROCESS


@pytest.mark.slow
def test_generated_capture_runs_in_a_folder_with_spaces_and_reruns_only_on_change(tmp_path):
    """generate + preprocess for real (test preset) in a path with spaces; then a changed generated image
    reruns preprocess alone, and a regenerated capture leaves nothing stale behind."""
    work = tmp_path / "work dir"
    _workflow_config(work, "synthetic")
    edit_yaml(work / PRESET, lambda p: p["synthetic"].update(cameras=4, frames=4, width=48, height=48))
    target = "results/synthetic/subject00/capture/report.json"

    def run() -> None:
        try:
            snakemake_run(work, target, "--cores", "2")
        except AssertionError as failed:
            logs = "\n".join(f"== {p}\n{p.read_text()[-2000:]}" for p in sorted(work.glob("results/**/logs/*.log")))
            raise AssertionError(f"{failed}\n{logs}") from None

    run()
    assert (work / target).is_file()
    assert scheduled(work, target) == {}
    image = work / "results" / "synthetic" / "data" / "subject00" / "images" / "cam00" / "00000000.jpg"
    stat = image.stat()
    os.utime(image, ns=(stat.st_atime_ns, stat.st_mtime_ns - 3600 * 10**9))
    assert scheduled(work, target) == {"preprocess_capture": 1}
    edit_yaml(work / PRESET, lambda p: p["synthetic"].update(seed=1))
    assert scheduled(work, target) == {"generate_capture": 1, "preprocess_capture": 1}
    run()
    # preprocess's manifest of the raw files was taken after generate rewrote them.
    assert scheduled(work, target) == {}


def test_evaluate_names_changed_levels_as_the_likely_cause(small_capture, tmp_path):
    renders = tmp_path / "renders" / "novel_view"
    for level in (0, 1):
        (renders / f"lod{level}").mkdir(parents=True)
    with pytest.raises(FileNotFoundError, match=r"LOD\(s\) \[2\] were not rendered; found lod\[0, 1\].*avatar\.levels"):
        evaluate_split(small_capture, renders, "novel_view", tmp_path / "metrics", EvaluateConfig(device="cpu"), [2])
    assert not (tmp_path / "metrics").exists()


def test_old_config_key_profile_names_its_new_name(recorded):
    code, output = snakemake_exit(recorded, TARGET, "--dry-run", "--config", "profile=test")
    assert code == 1
    assert ("config key `profile` is now `preset` (compute presets are config/presets/*.yaml, apart from Snakemake's "
            "profiles): use --config preset=test or `preset:` in your config file") in output


# Runs Snakemake's command line and reports whether anything imported torch meanwhile.
DAG_PROBE = """
import sys
import snakemake.cli
try:
    snakemake.cli.main(sys.argv[1:])
except SystemExit as done:
    print("exit", done.code, "torch", "torch" in sys.modules)
"""


def test_dag_building_imports_no_torch(recorded):
    """A dry run of the default target (the THuman4 reader's file checks included) and of the synthetic capture
    (the generator's settings) in a fresh interpreter: torch costs ~3 s per `snakemake` start, jobs import it."""
    env = {**os.environ, "PYTHONPATH": os.pathsep.join(filter(None, [str(REPO), os.environ.get("PYTHONPATH")]))}
    for target in ("all", "results/synthetic/subject00/capture/report.json"):
        done = subprocess.run([sys.executable, "-c", DAG_PROBE, target, "--dry-run", "--forceall", "--snakefile",
                               str(REPO / "Snakefile"), "--directory", str(recorded)],
                              capture_output=True, text=True, timeout=120, env=env)
        assert done.stdout.splitlines()[-1] == "exit 0 torch False", done.stdout[-3000:] + done.stderr[-3000:]
        assert "rule preprocess_capture:" in done.stdout


def test_animate_examples_render_a_turntable_and_the_shipped_demo_motion(recorded):
    assert scheduled(recorded, "animate_examples") == {"animate": 2, "animate_examples": 1}  # the fit is up to date
    output = snakemake_run(recorded, "animate_examples", "--dry-run", "--printshellcmds")
    commands = {}
    lines = [line.split("Shell command: ", 1)[1] for line in output.splitlines() if "Shell command: " in line]
    for command in (line for line in lines if line != "None"):  # animate_examples itself runs nothing
        words = shlex.split(command)
        commands[Path(words[words.index("--output") + 1]).name] = words
    assert sorted(commands) == ["demo", "turntable"]
    for clip, words in commands.items():
        assert words[words.index("--checkpoint") + 1] == f"results/thuman4/{SUBJECT}/pig/avatar.pt"
        assert words[words.index("--output") + 1] == f"results/thuman4/{SUBJECT}/pig/animate/{clip}"
    assert "--motion" not in commands["turntable"]
    motion = Path(commands["demo"][commands["demo"].index("--motion") + 1])
    assert motion.name == "demo.npz" and motion.is_file()
