"""`python -m aerec_viewer [SITE_OR_OUT] [options]`: the viewer without the `aerec` command."""

import sys

from .cli import main

sys.exit(main())
