"""``python3 -m leangate_client``: the same as the ``leangate-client`` command."""

import sys

from .cli import main

if __name__ == "__main__":
    sys.exit(main(prog="leangate-client"))
