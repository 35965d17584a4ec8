"""walkstream server: scene store, LOD selection, sessions and the websocket app."""
