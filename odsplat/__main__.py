"""`python -m odsplat`: the command line."""
from .cli import main

main(prog_name="odsplat")
