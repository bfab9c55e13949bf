"""Baselines FM-Fusion is compared with (paper Sec. V): `kimera`, the Kimera-style semantic mapper whose
instances come from clustering same-label voxels afterwards ("Cluster-All")."""
