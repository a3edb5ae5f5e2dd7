"""The command line: `cacc-bench` and its subcommands, the top layer (docs/contributing.md, Layers)."""
