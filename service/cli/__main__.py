from service.cli import run_program

run_program()
