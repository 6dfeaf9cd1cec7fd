"""softplc: a soft PLC whose control programs are Petri nets."""

__version__ = "0.1.0"
