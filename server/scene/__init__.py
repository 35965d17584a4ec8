"""Scene data: the SQLite scene store, LOD chain generation and the demo scene.

Import from the submodules (``server.scene.store``, ``server.scene.lod``,
``server.scene.demo``, ``server.scene.builder``); this package re-exports nothing.
"""
