#!/usr/bin/env bash
# Runs HERE, from the checkout's root, before run23/slots.sh: Snakemake 9.27.1 and what it imports, as wheels for the
# GPU machine's CPython 3.12 (about 12 MB), into .gpu/snakemake/ (carried with .gpu). PuLP (the ILP scheduler, 17 MB)
# is left out: slots.sh runs Snakemake's greedy scheduler. connection_pool has no wheel: built here (pure Python).
set -e
dest=.gpu/snakemake
mkdir -p "$dest"
pip download -q --no-deps --only-binary=:all: --python-version 3.12 --implementation cp --abi cp312 \
  --platform manylinux2014_x86_64 --platform manylinux_2_17_x86_64 --platform manylinux_2_28_x86_64 -d "$dest" \
  snakemake==9.27.1 platformdirs==4.14.8 immutables==0.21 ConfigArgParse==1.9.0 docutils==0.22.4 GitPython==3.2.1 \
  gitdb==4.0.12 smmap==5.0.3 humanfriendly==10.0 Jinja2==3.1.6 MarkupSafe==3.0.3 jsonschema==4.26.0 attrs==26.1.0 \
  jsonschema-specifications==2025.9.1 referencing==0.37.0 rpds-py==0.30.0 typing_extensions==4.15.0 \
  nbformat==5.11.1 fastjsonschema==2.22.3 jupyter_core==5.9.1 traitlets==5.15.0 packaging==25.0 psutil==7.2.2 \
  requests==2.34.2 charset-normalizer==3.4.7 idna==3.13 urllib3==2.7.0 certifi==2026.5.20 tenacity==9.2.1 \
  smart_open==7.7.1 wrapt==2.1.2 snakemake-interface-executor-plugins==9.4.0 argparse-dataclass==2.0.0 \
  snakemake-interface-common==1.23.0 throttler==1.2.3 snakemake-interface-storage-plugins==4.4.1 \
  snakemake-interface-report-plugins==1.3.0 snakemake-interface-logger-plugins==2.1.0 \
  snakemake-interface-scheduler-plugins==2.0.2 tabulate==0.10.0 yte==1.9.4 dpath==2.2.0 conda-inject==1.3.2 \
  sqlmodel==0.0.37 SQLAlchemy==2.0.58 greenlet==3.5.6 pydantic==2.13.4 annotated-types==0.7.0 \
  pydantic_core==2.46.4 typing-inspection==0.4.2
pip wheel -q --no-deps -w "$dest" connection_pool==0.0.3
ls "$dest" | wc -l | sed 's/$/ wheels in .gpu\/snakemake/'
