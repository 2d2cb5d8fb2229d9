"""Benchmark commands (``drivingscene bench <name>``). Each module: ``add_arguments`` and ``run``."""
