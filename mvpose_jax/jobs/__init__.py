"""Jobs: what one command runs, for the CLI, the experiments and the benchmarks alike.

Each job module takes one frozen config (plain values: file names, numbers, names) and returns
a result the caller prints or measures. The modules import nothing heavy at import time (jax,
flax, the readers are imported inside the run functions), so that building the command line's
parser from their configs and constants stays fast.
"""
