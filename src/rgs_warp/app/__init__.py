"""The application: command line, run folders, checkpoints, playback, evaluation of a run, report, viewer,
export, kernel precompile, evaluation suite; imports the library, never the other way."""
