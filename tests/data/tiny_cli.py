"""``python tests/data/tiny_cli.py ARGS...``: the headforge command line with
``load_data("tiny-nha")`` giving the tests' tiny head model (tests/conftest.py), for commands a
test runs in other processes (``torchrun ... tests/data/tiny_cli.py fit nha ...``)."""

import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from make_nha_reference import use_tiny_head  # noqa: E402

use_tiny_head()

from headforge.cli import main  # noqa: E402

sys.argv = ["headforge", *sys.argv[1:]]
main()
