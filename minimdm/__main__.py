"""``python -m minimdm ...`` runs the ``minimdm`` command (and ``torchrun -m minimdm train``)."""

from minimdm.cli import main

raise SystemExit(main())
