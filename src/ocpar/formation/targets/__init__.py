"""Formation targets: closed curves, surfaces with two parameters per agent, and slots."""
