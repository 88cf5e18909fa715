"""The napari face of napari-unwind: reader, writers, sample data and the Unwind dock (npe2 contributions)."""
