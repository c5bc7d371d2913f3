"""`python -m odsplat`: the command line."""
from odsplat.app.cli import main

if __name__ == "__main__":     # not when a spawned pool process imports this module again
    main(prog_name="odsplat")
