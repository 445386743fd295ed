"""Sub-commands of ``python -m dresg_addon``; see :mod:`dresg_addon.cli`."""
