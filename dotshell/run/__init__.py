"""The run directory and everything written into it: :class:`~dotshell.run.store.RunStore`,
the names in it (:class:`~dotshell.run.layout.RunLayout`), frames and TIFF pages, frame
checks, PLY clouds, generations and the run lifecycle."""
