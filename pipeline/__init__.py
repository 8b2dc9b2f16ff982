"""Ray (and MLflow) glue around the pure-PyTorch `aniformer` package."""
