"""One command-line entry point per pipeline stage (`python -m pig.stages.<stage> --help`)."""
