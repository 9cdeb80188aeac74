import sys

from mntes_stream.cli import main

sys.exit(main())
