"""pbrsr: PBR texture super-resolution for glTF assets (the PBR-SR method).

Everything that is not the job service lives here: asset I/O, the differentiable renderer,
image priors, losses, the optimizer, metrics and the CLI. This package never imports
``service`` or ``worker``.
"""

__version__ = "0.1.0"
