from midas_cli.commands.main import run

run()
