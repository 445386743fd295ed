"""The sub-commands of ``python -m dresg_addon`` (see :mod:`dresg_addon.cli`), one module each.

Each module adds its arguments to the parser and runs one engine call: reading files, calling the
method or an evaluation, writing results. The top layer: may import every other package; none imports it.
"""
