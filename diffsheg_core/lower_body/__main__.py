"""`python -m diffsheg_core.lower_body --capture TAKE.npz [--out FILE]`: build the lower-body library."""

from .capture import main

if __name__ == "__main__":
    raise SystemExit(main())
