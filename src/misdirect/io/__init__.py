"""Everything that crosses the boundary of the process: files in, files out.

``problem_file`` is the ``misdirect/v1`` format; ``grid_map`` its map form; ``storm`` builds
PRISM/DRN models through Storm; ``paynt`` reads and writes PAYNT's controllers and
``paynt_synthesis`` runs PAYNT; ``export`` writes models for other tools; ``files`` reads
untrusted input within limits and writes every output atomically.
"""
