"""The application on top of both packages: the `dimgestor` command (`cli`), `dimgestor generate` (`generate`)
and `dimgestor render` (`render`). It imports the model package (`dimgestor`) and the server (`streamer`); neither
imports it."""
