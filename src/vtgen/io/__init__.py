"""Layer 2, io: the one place that knows file formats.

Images, parquet tables and their columns, model files, params.yaml and its schema, atomic
output folders, report templates. Imports only :mod:`vtgen.core`.
"""
