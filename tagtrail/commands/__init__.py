"""The file-level commands of the CLI: init, demo, relocalize."""
