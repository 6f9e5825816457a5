"""The fleet map (contract section 7): stored building maps, the evidence of every bundle,
tracked changes confirmed by persistence, and versioned maps that Nav2's map_server loads.

The pipeline computes a bundle's :class:`~mapserver.fleet.observe.Observation` in a worker;
the main process hands it to :meth:`~mapserver.fleet.store.FleetStore.apply`, the only writer.
"""
