"""Recordings: MCAP writing and reading, inspection and recovery, the run metadata the recorder writes, and the
replay player with its log reading."""
