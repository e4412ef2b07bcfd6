"""The autocal REST job service (imported as ``autocal.service``); built in a later issue."""
