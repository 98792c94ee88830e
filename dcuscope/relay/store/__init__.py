"""Storage of runs, sessions, batches and clock history, behind one interface with one module per engine."""
