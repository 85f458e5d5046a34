"""Test-wide settings."""

import torch

# The networks are small: one intra-op thread is fastest on a 2-core machine and keeps CPU time
# predictable when other processes share it.
torch.set_num_threads(1)
