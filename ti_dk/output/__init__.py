"""What a run writes: HDF5 run files, openPMD snapshots, locks and paths (:mod:`.files`), PNG frames
and movies (:mod:`.render`), 1D moment profiles (:mod:`.profiles`)."""
