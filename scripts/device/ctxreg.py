"""`ctxreg` entry point on the device (register.cli:entry, as the console script does)."""
import sys
sys.argv[0] = "ctxreg"
from register.cli import entry
entry()
