"""What the commands do, as library calls: each module takes the options a command was given,
checks them, runs the work and writes its files; the CLI only parses and prints."""
