from imucal_cli.cli import main

main()
