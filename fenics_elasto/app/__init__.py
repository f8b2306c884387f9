"""The application: the command line, what each command does, pictures."""
