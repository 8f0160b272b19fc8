"""Worked examples of extending the package from outside its core, as a user's package would:
`camera` is a plug-in restricted area (zones drawn in a camera image) that scenarios load by
name through `zones.plugins.load_area`."""
