"""What comes in and goes out: probe logs (``probelog``: CSV/Parquet reading, limits, the
stations of a log), bags (``bag``: MCAP writing and reading, recovery, message definitions),
CDR decoding (``cdr``), the graph's topic names, message types and the one station-message
conversion (``topics``), the account of what a run read and wrote (``accounting``) and progress
bars (``progress``).

May import: ``core``, ``detect``.
"""
