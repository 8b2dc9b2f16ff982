"""The jobs' command-line and file-safety plumbing: arguments and configs (`args`), exits (`exits`), output
locks (`locks`) and output directories (`outputs`). The model core never imports it."""
