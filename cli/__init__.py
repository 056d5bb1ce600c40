"""mst.cli: the click commands (arguments, messages, exit codes) and the options they share.

May import every mst package; at module level only click and light helpers (heavy libraries are
imported inside the commands, so that ``mst --help`` stays fast). Nothing imports mst.cli.
"""
