"""Watching and joining a run: the browser viewer, the WebSocket gateway, Foxglove scenes, cameras."""
