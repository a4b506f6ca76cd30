"""Everything that crosses the boundary of the process: files in, files out.

``problem_file`` is the ``misdirect/v1`` format; ``grid_map`` its map form; ``storm`` builds
PRISM/DRN models through Storm, with ``storm_arrays`` (the matrix in bulk), ``storm_names``
(names of states, observations, actions) and ``storm_expressions`` (conditions, properties,
constants); ``paynt`` reads and writes PAYNT's controllers, ``paynt_model`` builds the model
as PAYNT does and ``paynt_synthesis`` runs PAYNT; ``export`` writes models for other tools;
``files`` reads untrusted input within limits and writes every output atomically.
"""
