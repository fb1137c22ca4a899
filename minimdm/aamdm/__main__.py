"""``python -m minimdm.aamdm train CONFIG [--out DIR] [--ship]``: train a motion AAMDM
(:func:`minimdm.cli.aamdm_main`, with the ``minimdm`` command's one error path)."""

import sys

from minimdm.cli import aamdm_main

if __name__ == "__main__":
    sys.exit(aamdm_main())
