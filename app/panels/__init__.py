"""UI panels, one per file; each ``draw(viewer)`` builds its imgui widgets and calls viewer actions."""
