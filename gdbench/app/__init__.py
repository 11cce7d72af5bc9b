"""The application: the command line, its commands, the viewer, export, and set-up's
prebuild of the cache."""
