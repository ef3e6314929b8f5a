"""The store's commands, apart from its core: each module is the body of one `occdata` command run on
a built store, and nothing in the build or the reader imports them (tests/test_import_contract.py).

`bev_gt` (`occdata bev-gt`), `visibility` (`occdata visibility`), `verify` and `verify_images`
(`occdata verify [--images]`), `info` (`occdata info` / `dump`), `check_projection`
(`occdata check-projection`). They were `occdata.store.bevgt`, `visibility_cmd`, `verify`,
`verify_images`, `inspect` and `draw` (docs/CHANGELOG.md lists every move)."""
