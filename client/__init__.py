"""The Python client SDK of the system (`push_client.push`), outside the common library; `shared` never imports it."""
