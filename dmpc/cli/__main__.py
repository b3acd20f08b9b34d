"""``python -m dmpc.cli``: the ``dmpc`` command."""
from dmpc.cli import main

main()
