"""Streams of frames: their tracker state in the ledger's database, so that any replica serves a stream's next frame
(``store``), the earlier frames a stream's detector reads (``history``), and a stream's recording (``recording``)."""
