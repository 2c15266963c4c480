"""The user-facing sub-commands of ``jaxmocap`` (one module each, registered in
:mod:`jaxmocap.cli`): ``calibrate``, ``colors``, ``track``, ``eval``."""
