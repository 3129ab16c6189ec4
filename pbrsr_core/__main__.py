"""`python -m pbrsr_core` is the `pbrsr` command."""

from .cli import main

main()
