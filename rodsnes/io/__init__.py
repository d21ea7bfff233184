"""Reading a scene from the options database (scene) and writing results (results)."""
