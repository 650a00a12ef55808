"""The command-line applications (``cochlea-run``, ``cochlea-model``, ``cochlea-codegen``) and
what a run leaves behind (the report: CSV, summary, figures). The top layer: nothing imports
it."""
