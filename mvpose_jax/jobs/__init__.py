"""Jobs: what one command runs, as one library call (a frozen config in, a result out).

The CLI parses options into a job's config, calls the job and prints its result; other callers
(the Pose2Sim demo benchmark, a batch runner) call the same function. The job configs hold plain
values (file names, numbers, names). Building the parser stays light: the job modules whose
configs the CLI reads at import (`common`, `adapt`, `smooth`, `train`, ...) import the pipeline
inside their run functions, and `infer`, `session`, `view` and `score` are imported only when
their command runs.
"""
