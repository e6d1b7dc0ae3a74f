"""What a scan leaves on disk: the scan folder and its store, the typed manifest, atomic writes
and the error tree of the store, and the writer thread that keeps a folder consistent.
"""
