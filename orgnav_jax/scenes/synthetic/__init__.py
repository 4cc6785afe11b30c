"""The procedural benchmark: rooms, objects, detector and global view from a seed.

    presets.py     the scene presets (rooms per split, feature widths)
    layout.py      room layouts and object placement; catalog.py: the objects
    geometry.py    states, transitions, camera, line of sight, visibility
    detector.py    simulated detections and appearance codes; global_view.py: 7x7 map codes
    builder.py     preset + seed -> rooms -> SceneSet (through sceneset/assemble.py)
    raw.py         the raw preset ('large'): decoded features streamed to disk
    cache.py       a preset's set built once into the cache; the set a process loaded
"""
