"""The `hrp2-drake` commands: one module a command. `add(commands)` registers its
parser, `run(args)` parses what the options say, calls the pipeline it runs (`tools/`,
`paper/`) and prints. A command imports no other command, only `options` (what they
share); nothing but `cli.py` imports a command."""
