"""Readers and writers: FITS, OpenEXR, PNG quicklooks; every write is atomic."""
