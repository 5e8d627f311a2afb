"""What every HTTP answer of the service is made of: the error bodies (``errors``, ``error_types``), the security
headers (``security_headers``) and what the service may say about names it did not choose (``public_text``)."""
