"""``python -m minimdm ...`` runs the ``minimdm`` command (and ``torchrun -m minimdm train``)."""

from minimdm.cli import main

if __name__ == "__main__":
    raise SystemExit(main())
