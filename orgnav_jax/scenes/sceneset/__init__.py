"""The SceneSet data model: what every scene source produces and every consumer reads.

    sceneset.py   the SceneSet pytree (flat state axis), its views and device copy
    fields.py     field names by axis, sentinels (UNREACHABLE, NO_ACTION), format name
    assemble.py   rooms -> SceneSet: the one assembly, the contract of a scene source
    expert.py     expert tables of padded rooms (JAX); flat.py: of flat rooms, old layout
    checks.py     SceneSet.validate: shapes, dtypes, values
    storage.py    save / load a directory of .npy files (memory-mapped)
    features.py   stored codes -> model inputs, inside jit; quantize.py: int8 storage
    keys.py       the authors' state keys "x|z|rotation|horizon"
    episodes.py   the EpisodeSet (episodes over one SceneSet) and its authors'-form records

Nothing here knows a scene source (scenes/synthetic, scenes/offline sit above it).
"""
