"""Jobs: what a command runs, as one library call each (a frozen config in, a result out), so
the CLI, the experiments and the benchmarks run the same code."""
