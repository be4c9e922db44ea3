"""The recording: the HDF5 recorder, its reader, checkpoints, segments and the results database."""
