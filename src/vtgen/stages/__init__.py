"""Layer 3, stages: one module per pipeline stage, each a plain function with explicit inputs,
outputs and parameters (``run_<stage>``). A stage imports core and io, never another stage;
what two stages share lives below them.
"""
