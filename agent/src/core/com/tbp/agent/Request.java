package com.tbp.agent;

import java.nio.ByteBuffer;
import java.nio.charset.CharacterCodingException;
import java.nio.charset.CodingErrorAction;
import java.nio.charset.StandardCharsets;
import java.util.Map;

/**
 * One request line, parsed: its id, op and the other fields (which each op reads what it needs
 * from, so unknown fields are ignored). A line that is not a JSON object with a valid id and a
 * string op is a {@link ErrorCode#BAD_REQUEST} answered with id 0.
 */
public final class Request {

    /** Ids are JSON integers a double represents exactly: 0 <= id < 2^53. */
    public static final long MAX_ID = 1L << 53;

    public final long id;
    public final String op;
    private final Map<String, Object> fields;

    private Request(long id, String op, Map<String, Object> fields) {
        this.id = id;
        this.op = op;
        this.fields = fields;
    }

    /** Parses one line (UTF-8, ending in '\n'). */
    @SuppressWarnings("unchecked")
    public static Request parse(byte[] line) throws AgentError {
        String text;
        try {
            text = StandardCharsets.UTF_8.newDecoder()
                    .onMalformedInput(CodingErrorAction.REPORT)
                    .onUnmappableCharacter(CodingErrorAction.REPORT)
                    .decode(ByteBuffer.wrap(line)).toString();
        } catch (CharacterCodingException e) {
            throw new AgentError(ErrorCode.BAD_REQUEST, "line is not UTF-8");
        }
        Object value;
        try {
            value = Json.parse(text);
        } catch (Json.SyntaxError e) {
            throw new AgentError(ErrorCode.BAD_REQUEST, "not JSON (" + e.getMessage() + "): " + excerpt(text));
        }
        if (!(value instanceof Map)) {
            throw new AgentError(ErrorCode.BAD_REQUEST, "line is a JSON " + kind(value) + ", not an object");
        }
        Map<String, Object> object = (Map<String, Object>) value;
        Object id = object.get("id");
        if (!(id instanceof Long) || (Long) id < 0 || (Long) id >= MAX_ID) {
            throw new AgentError(ErrorCode.BAD_REQUEST, "'id' must be a non-negative integer, got " + Json.excerpt(id));
        }
        Object op = object.get("op");
        if (!(op instanceof String)) {
            throw new AgentError(ErrorCode.BAD_REQUEST, "'op' must be a string, got " + Json.excerpt(op));
        }
        return new Request((Long) id, (String) op, object);
    }

    private static String excerpt(String text) {
        String trimmed = text.endsWith("\n") ? text.substring(0, text.length() - 1) : text;
        return trimmed.length() <= 80 ? trimmed : trimmed.substring(0, 80) + "...";
    }

    private static String kind(Object value) {
        if (value == null) {
            return "null";
        }
        if (value instanceof String) {
            return "string";
        }
        if (value instanceof Boolean) {
            return "boolean";
        }
        if (value instanceof Number) {
            return "number";
        }
        return "array";
    }

    /** Whether the request carries {@code name} (even as null). */
    public boolean has(String name) {
        return fields.containsKey(name);
    }

    /** A finite number field (booleans are not numbers). */
    public double number(String name) throws AgentError {
        Object value = fields.get(name);
        if (!(value instanceof Long || value instanceof Double)) {
            throw new AgentError(ErrorCode.BAD_REQUEST, op + ": '" + name + "' must be a number, got " + Json.excerpt(value));
        }
        double d = ((Number) value).doubleValue();
        if (Double.isNaN(d) || Double.isInfinite(d)) {
            throw new AgentError(ErrorCode.BAD_REQUEST, op + ": '" + name + "' must be finite, got " + value);
        }
        return d;
    }

    /** An integer field. */
    public long integer(String name) throws AgentError {
        Object value = fields.get(name);
        if (!(value instanceof Long)) {
            throw new AgentError(ErrorCode.BAD_REQUEST, op + ": '" + name + "' must be an integer, got " + Json.excerpt(value));
        }
        return (Long) value;
    }

    /** A string field. */
    public String text(String name) throws AgentError {
        Object value = fields.get(name);
        if (!(value instanceof String)) {
            throw new AgentError(ErrorCode.BAD_REQUEST, op + ": '" + name + "' must be a string, got " + Json.excerpt(value));
        }
        return (String) value;
    }
}
