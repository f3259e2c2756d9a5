"""Steps 4-5 of the method: the Euclidean upgrade H_A from GCPs, ICP fusion of date groups, the DSM."""
