"""One module per ``headforge`` command group; :mod:`headforge.cli` wires them."""
