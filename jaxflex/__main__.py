from jaxflex.app.cli import console

console()
