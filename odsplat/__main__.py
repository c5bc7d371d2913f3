"""`python -m odsplat`: the command line."""
from odsplat.app.cli import main

main(prog_name="odsplat")
