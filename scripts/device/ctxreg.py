"""`ctxreg` entry point on the device (register.cli:main, as the console script does)."""
import sys
sys.argv[0] = "ctxreg"
from register.cli import main
sys.exit(main())
