import sys
from learn.checkpoint import load_checkpoint
print("checkpoint iteration", load_checkpoint(sys.argv[1]).iteration)
