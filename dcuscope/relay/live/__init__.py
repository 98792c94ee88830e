"""What the relay holds of each run in memory: frames being paired, statistics, stored sequence numbers."""
