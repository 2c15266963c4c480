"""The sub-commands of ``jaxmocap``, one module each (registered in :mod:`jaxmocap.cli`):
``demo``, ``build_db`` (``build-db``), ``synth``, ``synth_world`` (``synth-world``),
``calibrate``, ``colors``, ``track``, ``evaluate`` (``eval``), ``body``, ``experiment``.
``_body`` holds the shared ``--body`` / ``--garment`` options. Library modules never import
this package (``tests/test_architecture.py``)."""
