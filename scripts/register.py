"""Run one experiment of the paper: ``python scripts/register.py [key=value ...]`` (same as ``indreg-register``)."""
from indreg.experiments.register import main

if __name__ == "__main__":
    main()
