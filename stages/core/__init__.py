"""Layer ``core``: errors that name file, problem and remedy; the settings base class; atomic and
staged outputs, metadata and the origin record; the one stage command-line wrapper. Imports
nothing else of the project, and no torch (the device helper imports it when called)."""
