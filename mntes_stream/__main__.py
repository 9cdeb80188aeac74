from mntes_stream.cli import run

run()
