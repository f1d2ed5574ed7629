"""The ``upcast`` subcommands, one module per job (``add_arguments`` and ``run``).

The top of the tree: may import every package; only ``server.cli`` imports it.
"""
