"""Benchmarks (``pbrsr bench ...``): each command runs its cases, prints a table and writes
JSON and plots. Built on ``pbrsr_core`` (and, for ``load``, the service and workers as
separate processes); ``pbrsr_core`` never imports it."""
