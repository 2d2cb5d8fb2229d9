"""Importers of real driving data into the frame-pair format: nuScenes, DDAD (DGP layout) and a
documented folder layout for your own rig (docs/importing.md). ``drivingscene import ...``."""
