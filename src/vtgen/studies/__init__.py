"""Layer 4, studies: experiments, the speed-accuracy trade-off, stability cases and their report.

They run the stages' public ``run_<stage>`` functions (the entries the stage table names),
never their private helpers.
"""
