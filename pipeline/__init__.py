"""dcuscope's pipeline framework: YAML configuration, pipeline building and running, the CLI."""
