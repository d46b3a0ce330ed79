"""`python -m dimgestor_app ...` runs the `dimgestor` command."""
import sys

from dimgestor_app.cli import main

sys.exit(main())
