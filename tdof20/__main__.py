"""``python -m tdof20 ...`` (and ``torchrun ... -m tdof20 train hff6dof ...``): the command line."""

from tdof20.cli import main

if __name__ == "__main__":
    main()
