"""A workflow job's processes end with the job.

Killing a job's shell (Snakemake's `bash -c ...`, by hand or by a runner) otherwise leaves its stage running as an
orphan, holding its output lock (and GPU slot) against the rerun until it finishes. The workflow marks its jobs'
environment (JOB_ENV=1, workflow/rules/common.smk); there the slot launcher (pig.gpu_slots) and every stage
(pig._cli.run_cli) ask the kernel to send them SIGTERM when their parent process ends (Linux's PR_SET_PDEATHSIG,
which the launcher's exec into the stage keeps). Only there: a stage started by hand under `nohup` must outlive its
terminal. The kernel releases the flock-based locks of a process that ends, so the rerun proceeds. No torch.
"""
from __future__ import annotations

import ctypes
import os
import signal
import sys

JOB_ENV = "PIG_WORKFLOW_JOB"
PR_SET_PDEATHSIG = 1  # linux/prctl.h


def end_with_parent(environ=os.environ) -> bool:
    """In a workflow job (JOB_ENV=1) on Linux: this process gets SIGTERM when its parent ends (and at once if that
    happens during this call; a parent gone before the interpreter got here goes unnoticed). Returns whether the
    request was made."""
    if environ.get(JOB_ENV) != "1" or not sys.platform.startswith("linux"):
        return False
    parent = os.getppid()
    libc = ctypes.CDLL(None, use_errno=True)
    if libc.prctl(PR_SET_PDEATHSIG, signal.SIGTERM, 0, 0, 0) != 0:
        errno = ctypes.get_errno()
        raise OSError(errno, f"prctl(PR_SET_PDEATHSIG) failed: {os.strerror(errno)}")
    if os.getppid() != parent:  # the parent ended between the two looks: the signal will not come
        os.kill(os.getpid(), signal.SIGTERM)
    return True
