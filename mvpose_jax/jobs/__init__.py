"""Jobs: what one command runs, as one library call (a frozen config in, a result out).

The CLI parses options into a job's config, calls the job and prints its result; other callers
(the Pose2Sim demo benchmark, a batch runner) call the same function. The job configs hold plain
values (file names, numbers, names); the CLI imports a job module only when its command runs, so
building the parser stays free of the pipeline's imports.
"""
