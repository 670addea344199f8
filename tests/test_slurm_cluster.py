"""The `test` preset's whole workflow on a real one-node Slurm cluster on 127.0.0.1, through
`--workflow-profile slurm` (workflow/profiles/slurm, found as profiles/slurm beside the Snakefile; docs/cluster.md's
command) and snakemake-executor-plugin-slurm.

The cluster is Debian's slurm-wlm and munge, started here as root: munged, slurmctld and slurmd in a temporary
folder, a slurm.conf at Slurm's default path (the executor strips SLURM_CONF from the job steps it starts). Job
accounting is the job completion log (jobcomp/filetxt), which `sacct --completion` reads without slurmdbd and a
database; the executor polls job states with squeue, as sacct without --completion needs slurmdbd. Where Slurm, the
executor or root is missing the test skips and says why (`.ci/run` installs Slurm where it can).
"""
from __future__ import annotations

import csv
import importlib.util
import os
import shutil
import signal
import socket
import subprocess
import sys
import time
from pathlib import Path

import pytest

from pig.config import load_preset
from pig.resources import rule_resources

REPO = Path(__file__).resolve().parent.parent
SLURM_CONF = Path("/etc/slurm/slurm.conf")  # Debian's compiled-in default
MARK = "# written by pig's tests/test_slurm_cluster.py"
TOOLS = ("munged", "mungekey", "slurmctld", "slurmd", "sinfo", "sbatch", "squeue", "sacct", "scancel")
# Jobs of the default target with the test preset (2 LODs, 2 held-out splits, one variant): the main and regions
# tables, the montages and the report's turntable.
JOBS = {"generate_capture": 1, "preprocess_capture": 1, "fit_avatar": 1, "render_split": 2, "evaluate": 2,
        "montage_split": 2, "make_tables": 1, "make_table": 1, "animate": 1}


def skip_reason() -> str | None:
    missing = [tool for tool in TOOLS if shutil.which(tool) is None]
    if missing:
        return f"Slurm is not installed ({', '.join(missing)} not found; Debian: apt-get install slurm-wlm munge)"
    if importlib.util.find_spec("snakemake_executor_plugin_slurm") is None:
        return "snakemake-executor-plugin-slurm is not installed (pip install -e '.[slurm]')"
    if os.geteuid() != 0:
        return "starting munged, slurmctld and slurmd needs root"
    if (SLURM_CONF.exists() and MARK not in SLURM_CONF.read_text()) or "SLURM_CONF" in os.environ:
        configured = os.environ.get("SLURM_CONF", SLURM_CONF)
        return f"a Slurm cluster is configured here ({configured}): the test leaves it alone"
    return None


SKIP = skip_reason()
pytestmark = [pytest.mark.slow, pytest.mark.skipif(SKIP is not None, reason=str(SKIP))]


def free_port() -> int:
    with socket.socket() as probe:
        probe.bind(("127.0.0.1", 0))
        return probe.getsockname()[1]


def slurm_conf(root: Path) -> str:
    return f"""{MARK}: a one-node cluster on 127.0.0.1 for the test's lifetime
ClusterName=pigtest
SlurmctldHost=localhost(127.0.0.1)
SlurmctldPort={free_port()}
SlurmdPort={free_port()}
SlurmUser=root
SlurmdUser=root
AuthType=auth/munge
AuthInfo=socket={root}/munge.socket
CredType=cred/munge
StateSaveLocation={root}/state
SlurmdSpoolDir={root}/spool
SlurmctldPidFile={root}/slurmctld.pid
SlurmdPidFile={root}/slurmd.pid
SlurmctldLogFile={root}/slurmctld.log
SlurmdLogFile={root}/slurmd.log
ProctrackType=proctrack/linuxproc
TaskPlugin=task/none
SelectType=select/cons_tres
SelectTypeParameters=CR_Core_Memory
MpiDefault=none
ReturnToService=2
JobAcctGatherType=jobacct_gather/none
AccountingStorageType=accounting_storage/none
JobCompType=jobcomp/filetxt
JobCompLoc={root}/jobcomp.txt
MinJobAge=3600
# Four CPUs on two cores: the jobs mostly wait on Python start-up, and independent ones then overlap.
SlurmdParameters=config_overrides
NodeName=localhost NodeAddr=127.0.0.1 CPUs=4 RealMemory=8000 State=UNKNOWN
PartitionName=debug Nodes=localhost Default=YES MaxTime=INFINITE State=UP
"""


def stop(process: subprocess.Popen) -> None:
    if process.poll() is None:
        process.send_signal(signal.SIGTERM)
        try:
            process.wait(timeout=15)
        except subprocess.TimeoutExpired:
            process.kill()
            process.wait()


@pytest.fixture(scope="module")
def cluster(tmp_path_factory):
    """A running cluster (munged, slurmctld, slurmd); yields its folder, stops the daemons it started after."""
    root = tmp_path_factory.mktemp("slurm")
    root.chmod(0o755)  # munged checks that its socket's folder is reachable
    for name in ("state", "spool"):
        (root / name).mkdir()
    subprocess.run(["mungekey", "--create", f"--keyfile={root}/munge.key"], check=True)
    daemons = []
    try:
        SLURM_CONF.parent.mkdir(parents=True, exist_ok=True)
        SLURM_CONF.write_text(slurm_conf(root))
        quiet = {"stdout": subprocess.DEVNULL, "stderr": subprocess.DEVNULL}  # each daemon logs to a file here
        daemons.append(subprocess.Popen(
            ["munged", "--foreground", "--force", f"--key-file={root}/munge.key", f"--socket={root}/munge.socket",
             f"--pid-file={root}/munged.pid", f"--log-file={root}/munged.log", f"--seed-file={root}/munged.seed"],
            **quiet))
        deadline = time.monotonic() + 30
        while not (root / "munge.socket").exists():
            assert time.monotonic() < deadline and daemons[0].poll() is None, (root / "munged.log").read_text()
            time.sleep(0.1)
        daemons.append(subprocess.Popen(["slurmctld", "-D", "-f", str(SLURM_CONF)], **quiet))
        daemons.append(subprocess.Popen(["slurmd", "-D", "-N", "localhost", "-f", str(SLURM_CONF)], **quiet))
        while subprocess.run(["sinfo", "-h", "-o", "%t"], capture_output=True, text=True).stdout.strip() != "idle":
            if time.monotonic() > deadline or any(d.poll() is not None for d in daemons):
                logs = "\n".join(f"== {p.name}\n{p.read_text()[-2000:]}" for p in sorted(root.glob("*.log")))
                pytest.fail(f"the Slurm cluster did not come up within 30 s:\n{logs}")
            time.sleep(0.5)
        yield root
    finally:
        subprocess.run(["scancel", "--user=root"], capture_output=True)  # jobs of this cluster only
        for daemon in reversed(daemons):
            stop(daemon)
        if SLURM_CONF.exists() and MARK in SLURM_CONF.read_text():
            SLURM_CONF.unlink()


def sacct_jobs() -> dict[str, dict[str, str]]:
    """{job id: row} of every job in the cluster's completion log, through sacct."""
    out = subprocess.run(["sacct", "--completion", "--parsable2", "--format=JobIDRaw,JobName,State,NCPUS,Timelimit"],
                         capture_output=True, text=True, check=True).stdout
    return {row["JobIDRaw"]: row for row in csv.DictReader(out.splitlines(), delimiter="|")}


def test_workflow_runs_on_slurm(cluster, tmp_path):
    work = tmp_path / "work"
    work.mkdir()
    (work / "config").symlink_to(REPO / "config")
    env = {**os.environ, "PYTHONPATH": os.pathsep.join(filter(None, [str(REPO), os.environ.get("PYTHONPATH")]))}
    command = [sys.executable, "-m", "snakemake", "--snakefile", str(REPO / "Snakefile"),
               "--workflow-profile", "slurm",
               "--config", "preset=test", "dataset=synthetic", "variants=[pig]",
               # This cluster's particulars: no accounts, no slurmdbd; quick first status check.
               "--slurm-no-account", "--slurm-status-command", "squeue",
               "--slurm-init-seconds-before-status-checks", "1", "--slurm-keep-successful-logs"]
    started = time.monotonic()
    # 4 to 5 minutes on two busy cores: each job starts Snakemake twice (the job, then its step), and the executor
    # checks job states 1, 12, 33, 64 s after the last job ended.
    done = subprocess.run(command, cwd=work, env=env, capture_output=True, text=True, timeout=480)
    wall = time.monotonic() - started
    job_logs = sorted(work.glob(".snakemake/slurm_logs/rule_*/**/*.log"))
    logs = "\n".join(f"== {p}\n{p.read_text()[-1500:]}" for p in [*job_logs, *work.glob("results/**/logs/*.log")])
    assert done.returncode == 0, f"{done.stderr[-4000:]}\n{logs}"

    # Every job went through Slurm: one sacct record per Snakemake job, each COMPLETED, named by the run.
    by_rule = {}
    for log in job_logs:
        by_rule.setdefault(log.relative_to(work / ".snakemake" / "slurm_logs").parts[0][len("rule_"):], []).append(
            log.stem)
    assert {rule: len(ids) for rule, ids in by_rule.items()} == JOBS
    records = sacct_jobs()
    ours = {job for ids in by_rule.values() for job in ids}
    assert ours <= set(records), (ours, records)
    assert {records[job]["State"] for job in ours} == {"COMPLETED"}
    assert len({records[job]["JobName"] for job in ours}) == 1  # the executor names jobs by its run id
    # ... asking for what the test preset's `resources:` section gives each rule.
    preset = load_preset("test")
    for rule, ids in by_rule.items():
        if rule == "generate_capture":  # sized from the `synthetic` section
            continue
        wanted = rule_resources(preset, rule)
        for job in ids:
            assert (records[job]["NCPUS"], records[job]["Timelimit"]) == (str(wanted.threads), str(wanted.runtime))

    tables = work / "results" / "tables"
    with open(tables / "synthetic.csv") as table:
        assert "pig" in {row["variant"] for row in csv.DictReader(table)}
    for name in ("synthetic.md", "synthetic_lod.csv", "synthetic_lod.md", "synthetic_training.png"):
        assert (tables / name).stat().st_size > 0
    print(f"Slurm run: {wall:.0f} s wall, jobs (id, rule): "
          + ", ".join(f"{job} {rule}" for rule, ids in by_rule.items() for job in sorted(ids, key=int)))
