"""`python -m experiments <command> [options]`: the commands' entry point (`experiments.cli`)."""
from experiments.cli import main

if __name__ == "__main__":
    main()
