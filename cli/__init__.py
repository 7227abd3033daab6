"""The ``bodynet`` command: one entry point, one subcommand per service."""
